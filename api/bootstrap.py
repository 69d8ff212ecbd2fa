"""Creating the first tenants and keys (the `midview` admin CLI and the embedded default use these)."""

from __future__ import annotations

import logging

import sqlalchemy as sa
from sqlalchemy.orm import Session

from shared.db import crud
from shared.db.models import ApiKey, Tenant

log = logging.getLogger("midview.api")


def create_tenant_with_key(
    session: Session, name: str, key_name: str = "default", pepper: str | None = None
) -> str:
    """Create a tenant and one API key; return the plaintext key (shown once, only its hash is stored).
    ConflictError if the tenant exists. The caller commits."""
    tenant = crud.create_tenant(session, name)
    _, plaintext = crud.create_api_key(session, tenant.id, key_name, pepper=pepper)
    return plaintext


def ensure_api_key(session: Session, tenant_name: str, plaintext: str, pepper: str | None = None) -> Tenant:
    """Make sure a given plaintext key authenticates tenant_name (created if missing); a key that exists
    but was revoked stays revoked. Idempotent; the caller commits."""
    tenant = session.scalar(sa.select(Tenant).where(Tenant.name == tenant_name))
    if tenant is None:
        tenant = crud.create_tenant(session, tenant_name)
    key_hash = crud.hash_api_key(plaintext, pepper)
    existing = session.scalar(sa.select(ApiKey).where(ApiKey.key_hash == key_hash))
    if existing is None:
        session.add(
            ApiKey(
                tenant_id=tenant.id,
                name="bootstrap",
                prefix=plaintext[: crud.API_KEY_SHOWN],
                key_hash=key_hash,
            )
        )
        session.flush()
        log.info(
            "bootstrap API key %s... created for tenant %r", plaintext[: crud.API_KEY_SHOWN], tenant_name
        )
    elif existing.tenant_id != tenant.id:
        log.warning("bootstrap API key belongs to another tenant than %r; left as it is", tenant_name)
    return tenant
