"""The Python client (client/) against the API in-process, on both backends (SQLite + local storage:
parts through the API; PostgreSQL + SeaweedFS: parts to presigned S3 URLs): its contract with the
OpenAPI schema, resumed uploads, idempotent submission, checked downloads, manifests, CLI errors."""

from __future__ import annotations

import hashlib
import json
import typing
import uuid
from pathlib import Path

import pytest
from typer.testing import CliRunner

from client import ApiError, MidviewClient, Survey, download_job, read_manifest, submit_survey, upload_image
from client import http as client_http
from client.survey import SubmitProgress
from shared.db import crud
from shared.storage.keys import job_key


def _mv(env, tenant) -> MidviewClient:
    return MidviewClient("http://testserver", tenant.key, http=env.client)


def _survey_folder(root: Path, make_jpeg, aerial: int = 3, ground: int = 2) -> Path:
    """A survey on disk: images/{aerial,ground}, pos.csv, cameras.json (test JPEGs, 64 x 48)."""
    names = []
    for image_set, n in (("aerial", aerial), ("ground", ground)):
        (root / image_set).mkdir(parents=True, exist_ok=True)
        for i in range(n):
            (root / image_set / f"{image_set[0].upper()}{i + 1}.jpg").write_bytes(make_jpeg(seed=7 * i + n))
            names.append(f"{image_set}/{image_set[0].upper()}{i + 1}.jpg")
    rows = "".join(f"{n},{55.7 + i * 1e-4:.7f},13.19,{100 + i:.2f}\n" for i, n in enumerate(names))
    (root / "pos.csv").write_text("name,lat,lon,h\n" + rows)
    cam = {"model": "PINHOLE", "width": 64, "height": 48, "params": [60.0, 60.0, 32.0, 24.0]}
    (root / "cameras.json").write_text(json.dumps({"aerial": cam, "ground": cam}))
    return root


def _survey(root: Path, name: str | None = None, **options) -> Survey:
    return Survey(
        name=name or f"s-{uuid.uuid4().hex[:8]}",
        aerial=root / "aerial",
        ground=root / "ground",
        pos=root / "pos.csv",
        cameras=root / "cameras.json",
        options=options,
    )


def test_every_route_the_client_calls_is_in_the_openapi_schema(api_env) -> None:
    """The OpenAPI schema is the contract: each route the client calls exists with its method, and the
    fields the client's types declare are in the response models."""
    schema = api_env.client.get("/openapi.json").json()
    for method, path in client_http.ENDPOINTS:
        assert method.lower() in schema["paths"].get(path, {}), (method, path)
    models = schema["components"]["schemas"]
    for typed, model in [
        (client_http.Project, "ProjectOut"),
        (client_http.Image, "ImageOut"),
        (client_http.Upload, "UploadOut"),
        (client_http.Job, "JobDetail"),
        (client_http.Artifact, "ArtifactOut"),
        (client_http.Campaign, "CampaignDetail"),
    ]:
        assert set(typing.get_type_hints(typed)) <= set(models[model]["properties"]), model


def test_an_interrupted_multipart_upload_resumes_with_the_missing_parts(api_env, make_jpeg, tmp_path) -> None:
    t = api_env.tenant()
    mv = _mv(api_env, t)
    pid = mv.create_project(f"big-{uuid.uuid4().hex[:6]}")["id"]
    data = make_jpeg(width=640, height=480, padding=6_000_000)  # two parts of 5 MiB
    path = tmp_path / "A1.jpg"
    path.write_bytes(data)
    # a client killed after its first part: the upload is open, part 2 is missing
    digest = hashlib.sha256(data).hexdigest()
    up = mv.create_upload(pid, "aerial/A1.jpg", len(data), digest)
    assert up["part_count"] == 2
    mv.put_part(pid, up["id"], 1, data[: up["part_size"]])
    sent = []
    res = upload_image(mv, pid, "aerial/A1.jpg", path, on_part=lambda *a: sent.append(a[1]))
    assert (res.state, res.parts_sent, res.part_count, sent) == ("resumed", 1, 2, [2])
    assert res.bytes_sent == len(data) - up["part_size"]
    [image] = mv.images(pid, "aerial")
    assert image["sha256"] == digest and image["size_bytes"] == len(data)
    assert mv.uploads(pid) == []
    again = upload_image(mv, pid, "aerial/A1.jpg", path)
    assert again.state == "present" and again.bytes_sent == 0
    other = tmp_path / "other.jpg"
    other.write_bytes(make_jpeg(seed=99))
    with pytest.raises(ValueError, match="another image of this name"):
        upload_image(mv, pid, "aerial/A1.jpg", other)


class _KillAfter(SubmitProgress):
    """Raises after n files, as a client killed midway through its uploads."""

    def __init__(self, n: int) -> None:
        self.n, self.states = n, []

    def file_done(self, result, nbytes) -> None:
        self.states.append(result.state)
        if len(self.states) == self.n:
            raise KeyboardInterrupt


def test_a_repeated_submission_makes_no_second_job(api_env, make_jpeg, tmp_path) -> None:
    t = api_env.tenant()
    mv = _mv(api_env, t)
    survey = _survey(_survey_folder(tmp_path, make_jpeg), splat_steps=500)
    killed = _KillAfter(2)
    with pytest.raises(KeyboardInterrupt):
        submit_survey(mv, survey, progress=killed)
    resumed = _KillAfter(0)
    job = submit_survey(mv, survey, progress=resumed)
    assert resumed.states == ["present", "present", "uploaded", "uploaded", "uploaded"]
    assert job["key"] == survey.default_key() and job["options"]["splat_steps"] == 500
    again = _KillAfter(0)
    assert submit_survey(mv, survey, progress=again)["id"] == job["id"] and again.states == []
    project = mv.projects(survey.name)[0]
    assert len(mv.jobs(project["id"])) == 1
    assert [c for c in api_env.dispatcher.calls if c[:2] == ("submit", job["id"])] == [
        ("submit", job["id"], None)
    ]
    # other options: another key, another job on the same project (nothing uploaded twice)
    survey.options = {"splat_steps": 600}
    second = submit_survey(mv, survey, progress=(p := _KillAfter(0)))
    assert second["id"] != job["id"] and set(p.states) == {"present"}
    # a key chosen by the client
    assert submit_survey(mv, survey, key="run-1")["key"] == "run-1"
    assert submit_survey(mv, survey, key="run-1")["id"] == mv.jobs(project["id"], key="run-1")[0]["id"]


def test_download_checks_digests_and_skips_what_is_there(api_env, make_jpeg, tmp_path) -> None:
    from conftest import jobbable_project

    t = api_env.tenant()
    mv = _mv(api_env, t)
    pid = jobbable_project(api_env.client, t.headers, make_jpeg)
    jid = mv.create_job(pid)["id"]
    blobs = {"combined/report.json": b'{"ok": 1}', "combined/gis/cameras.geojson": b'{"type": "x"}'}
    for name, data in blobs.items():
        key = job_key(t.id, pid, jid, name.split("/")[0], name.split("/", 1)[1])
        api_env.storage.put_bytes(key, data)
        with api_env.session() as s:
            crud.record_artifact(s, jid, "report", name, key, len(data), hashlib.sha256(data).hexdigest())
            s.commit()
    got = download_job(mv, jid, tmp_path / "out")
    assert {p.relative_to((tmp_path / "out").resolve()).as_posix(): p.read_bytes() for p in got} == blobs
    only = download_job(mv, jid, tmp_path / "only", ["combined/gis/*"])
    assert [p.name for p in only] == ["cameras.geojson"]
    # a file already there with the right digest is kept; a corrupted one is fetched again
    (tmp_path / "out" / "combined" / "report.json").write_bytes(b"broken")
    download_job(mv, jid, tmp_path / "out")
    assert (tmp_path / "out" / "combined" / "report.json").read_bytes() == blobs["combined/report.json"]
    with api_env.session() as s:  # the listing's digest does not match the stored bytes
        crud.record_artifact(s, jid, "report", "combined/report.json", key, 9, "0" * 64)
        s.commit()
    with pytest.raises(ValueError, match="do not match"):
        download_job(mv, jid, tmp_path / "bad", ["combined/report.json"])


def test_api_errors_say_what_the_service_answered(api_env) -> None:
    t = api_env.tenant()
    mv = _mv(api_env, t)
    with pytest.raises(ApiError) as e:
        mv.job("no-such-job")
    assert e.value.status == 404 and "not found" in str(e.value) and "/jobs/no-such-job" in str(e.value)
    bad = MidviewClient("http://testserver", "wrong-key", http=api_env.client)
    with pytest.raises(ApiError) as e:
        bad.projects()
    assert e.value.status == 401


def test_manifests_csv_and_yaml(tmp_path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "c.csv").write_text(
        'name,aerial,ground,pos,options\nsite-1,a,g,p.csv,"{""splat_steps"": 500}"\nsite-2,a,,p.csv,\n'
    )
    m = read_manifest(tmp_path / "c.csv", max_concurrent=3)
    assert (m.name, m.max_concurrent, [s.name for s in m.surveys]) == ("c", 3, ["site-1", "site-2"])
    assert m.surveys[0].aerial == (tmp_path / "a").resolve() and m.surveys[1].ground is None
    assert m.surveys[0].options == {"splat_steps": 500} and m.surveys[1].options == {}
    (tmp_path / "c.yaml").write_text(
        "name: spring\nmax_concurrent: 4\noptions: {seed: 1}\n"
        "surveys:\n  - {name: x, aerial: a, ground: g, pos: p.csv, options: {seed: 2, splat_steps: 900}}\n"
        "  - {name: y, aerial: a, ground: g, pos: p.csv}\n"
    )
    y = read_manifest(tmp_path / "c.yaml")
    assert (y.name, y.max_concurrent) == ("spring", 4)
    assert [s.options for s in y.surveys] == [{"seed": 2, "splat_steps": 900}, {"seed": 1}]
    for text, message in [
        ("name,aerial,pos,colour\nx,a,p,red\n", "unknown column"),
        ("name,aerial,pos\nx,,p\n", "missing aerial"),
        ("name,aerial,pos\nx,a,p\nx,a,p\n", "unique"),
        ('name,aerial,pos,options\nx,a,p,"{nope"\n', "not a JSON object"),
        ("name,aerial,pos\n", "no surveys"),
    ]:
        (tmp_path / "bad.csv").write_text(text)
        with pytest.raises(ValueError, match=message):
            read_manifest(tmp_path / "bad.csv")


def test_cli_client_errors_are_messages_with_an_exit_code(tmp_path, make_jpeg) -> None:
    """Bad local input fails before any request (the server here does not exist)."""
    from cli.main import app

    root = _survey_folder(tmp_path, make_jpeg)
    runner = CliRunner()
    env = {"MIDVIEW_SERVER": "http://127.0.0.1:9", "MIDVIEW_API_KEY": "k"}
    r = runner.invoke(
        app, ["submit", str(tmp_path / "nope"), str(root / "ground"), str(root / "pos.csv")], env=env
    )
    assert r.exit_code == 2 and "is not a folder" in r.output
    (tmp_path / "empty").mkdir()
    r = runner.invoke(
        app, ["submit", str(tmp_path / "empty"), str(root / "ground"), str(root / "pos.csv")], env=env
    )
    assert r.exit_code == 2 and "no .jpg" in r.output
    r = runner.invoke(
        app, ["submit", *(str(root / x) for x in ("aerial", "ground", "pos.csv")), "-o", "x"], env=env
    )
    assert r.exit_code == 2 and "NAME=VALUE" in r.output
    r = runner.invoke(app, ["campaign", "submit", str(tmp_path / "none.csv")], env=env)
    assert r.exit_code == 2 and "none.csv" in r.output
