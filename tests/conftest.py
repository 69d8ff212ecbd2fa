"""Shared fixtures."""

from servers import postgres_server, postgres_url, redis_url, s3_server  # noqa: F401
