"""The label store: SQLModel tables, engine/session helpers and schema migrations.

`app.store.models` holds the tables (`app.store.columns` their column types and shared columns),
`app.store.db` the engine (`get_engine`, `session_scope`, `get_session`, `init_db`) and
`app.store.migrations` the schema version mechanism. This package imports nothing of `app` but
`app.core`.
"""
