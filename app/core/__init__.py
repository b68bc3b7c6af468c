"""Settings, errors and logging shared by every layer; imports nothing else of `app`."""
