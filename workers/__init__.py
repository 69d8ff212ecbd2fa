"""Celery workers running the pipeline stages of the midview service."""
