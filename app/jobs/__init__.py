"""Persistent jobs: a queue in SQLite, worker processes, and the tasks they run."""
