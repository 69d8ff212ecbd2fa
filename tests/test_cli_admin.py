"""`midview admin`: tenants, keys and webhook secrets made and revoked from the command line, checked
against the API on the same database."""

from __future__ import annotations

import json

from fastapi.testclient import TestClient
from typer.testing import CliRunner

from api.config import ApiSettings
from api.main import create_app
from cli.main import app
from shared.db.session import upgrade_database


def _admin(url: str, *args: str):
    return CliRunner().invoke(app, ["admin", *args, "--database-url", url])


def test_admin_round_trip(tmp_path):
    url = f"sqlite:///{tmp_path / 'midview.db'}"
    upgrade_database(url)
    r = _admin(url, "tenant-create", "acme", "--json")
    assert r.exit_code == 0, r.output
    (made,) = json.loads(r.output)
    key = made["api_key"]
    assert key.startswith("mv_")
    assert key.encode() not in (tmp_path / "midview.db").read_bytes()  # only its hash is stored
    assert _admin(url, "tenant-create", "acme").exit_code == 2  # taken

    settings = ApiSettings(data_dir=tmp_path, database_url=url, storage="local", storage_root=tmp_path / "s")
    with TestClient(create_app(settings)) as c:
        auth = {"Authorization": f"Bearer {key}"}
        assert c.get("/projects", headers=auth).status_code == 200
        hook = c.post("/webhooks", json={"url": "https://hooks.example.com/x"}, headers=auth).json()

        r = _admin(url, "key-create", "acme", "--name", "ci", "--json")
        second = json.loads(r.output)[0]["api_key"]
        keys = json.loads(_admin(url, "keys", "acme", "--json").output)
        assert [k["name"] for k in keys] == ["default", "ci"] and all(k["revoked_at"] is None for k in keys)
        assert all("api_key" not in k for k in keys)
        assert _admin(url, "key-revoke", made["key_id"]).exit_code == 0
        cache = c.app.state.key_cache  # the API remembers keys for auth_cache_s: let that time pass
        clock = cache.clock
        cache.clock = lambda: clock() + settings.auth_cache_s + 0.01
        assert c.get("/projects", headers=auth).status_code == 401
        assert c.get("/projects", headers={"Authorization": f"Bearer {second}"}).status_code == 200

        tenants = json.loads(_admin(url, "tenants", "--json").output)
        assert [(t["tenant"], t["active_keys"]) for t in tenants] == [("acme", 1)]

        r = _admin(url, "webhook-rotate", hook["id"], "--json")
        assert r.exit_code == 0 and json.loads(r.output)[0]["secret"] not in (hook["secret"], "")

    for bad in (("keys", "nobody"), ("key-revoke", "nokey"), ("webhook-rotate", "nohook")):
        r = _admin(url, *bad)
        assert r.exit_code == 2 and "error:" in r.output, bad


def test_admin_names_an_unreachable_database(tmp_path):
    r = _admin("postgresql+psycopg2://nobody@127.0.0.1:1/none", "tenants")
    assert r.exit_code == 2 and "error: database" in r.output
