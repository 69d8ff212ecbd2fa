"""The REST API (FastAPI) of the midview service."""
