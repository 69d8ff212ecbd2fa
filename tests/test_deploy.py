"""Deployment files: the compose file validates; the Kubernetes manifests parse and wire every queue."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from shared.job_options import STAGE_QUEUES

ROOT = Path(__file__).resolve().parents[1]


def _compose_cmd() -> list[str] | None:
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if (
        shutil.which("docker")
        and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0
    ):
        return ["docker", "compose"]
    return None


def test_compose_config_validates():
    cmd = _compose_cmd()
    if cmd is None:
        pytest.skip("neither docker-compose nor the docker compose plugin is installed")
    r = subprocess.run([*cmd, "config", "-q"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_compose_runs_a_worker_per_queue():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert {"postgres", "redis", "minio", "createbucket", "migrate", "api", "beat"} <= set(services)
    for queue in set(STAGE_QUEUES.values()):
        command = services[f"worker-{queue}"]["command"]
        assert command[command.index("-Q") + 1] == queue
    gpu = services["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"][0]
    assert gpu["driver"] == "nvidia" and "gpu" in gpu["capabilities"]


def test_kubernetes_workers_scale_on_their_queue():
    k8s = ROOT / "deploy" / "k8s"
    docs = [d for f in sorted(k8s.glob("*.yaml")) for d in yaml.safe_load_all(f.read_text()) if d]
    kustomized = set(yaml.safe_load((k8s / "kustomization.yaml").read_text())["resources"])
    assert kustomized == {f.name for f in k8s.glob("*.yaml")} - {"kustomization.yaml"}
    scaled = {d["metadata"]["name"]: d for d in docs if d["kind"] == "ScaledObject"}
    for queue in set(STAGE_QUEUES.values()):
        trigger = scaled[f"midview-worker-{queue}"]["spec"]["triggers"][0]
        assert trigger["type"] == "redis" and trigger["metadata"]["listName"] == queue
