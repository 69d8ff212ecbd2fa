"""Deployment files: the compose file validates; the Kubernetes manifests parse and wire every queue."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from services.pipeline import STAGE_QUEUES
from workers.celery_app import CONTROL_QUEUE, DELIVER_WEBHOOKS, RECONCILE, TASK_QUEUES

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
    assert {TASK_QUEUES[RECONCILE], TASK_QUEUES[DELIVER_WEBHOOKS]} == {CONTROL_QUEUE}
    control = services["worker-control"]["command"]  # the periodic tasks never wait behind a stage
    assert control[control.index("-Q") + 1] == CONTROL_QUEUE
    gpu = services["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"][0]
    assert gpu["driver"] == "nvidia" and "gpu" in gpu["capabilities"]


def test_the_image_serves_the_api_with_a_bounded_request_head():
    """The Dockerfile's uvicorn command carries api.config.server_flags at the defaults."""
    import json

    from api.config import ApiSettings, server_flags

    text = (ROOT / "deploy" / "Dockerfile").read_text().replace("\\\n", "")
    cmd = json.loads(next(line for line in text.splitlines() if line.startswith("CMD "))[4:])
    flags = server_flags(ApiSettings.model_construct())
    assert any(cmd[i : i + len(flags)] == flags for i in range(len(cmd))), cmd


def test_kubernetes_workers_scale_on_their_queue():
    k8s = ROOT / "deploy" / "k8s"
    docs = [d for f in sorted(k8s.glob("*.yaml")) for d in yaml.safe_load_all(f.read_text()) if d]
    kustomized = set(yaml.safe_load((k8s / "kustomization.yaml").read_text())["resources"])
    assert kustomized == {f.name for f in k8s.glob("*.yaml")} - {"kustomization.yaml"}
    scaled = {d["metadata"]["name"]: d for d in docs if d["kind"] == "ScaledObject"}
    for queue in set(STAGE_QUEUES.values()):
        trigger = scaled[f"midview-worker-{queue}"]["spec"]["triggers"][0]
        assert trigger["type"] == "redis" and trigger["metadata"]["listName"] == queue
    control = next(d for d in docs if d.get("metadata", {}).get("name") == "midview-worker-control")
    assert control["kind"] == "Deployment" and control["spec"]["replicas"] >= 1
    command = control["spec"]["template"]["spec"]["containers"][0]["command"]
    assert command[command.index("-Q") + 1] == CONTROL_QUEUE
    assert "midview-worker-control" not in scaled  # never scaled to zero


# Python versions an Ubuntu base image has in its own archive (apt), by the CUDA image tag's suffix
UBUNTU_PYTHONS = {"ubuntu22.04": {"3.10", "3.11"}, "ubuntu24.04": {"3.12"}}
UBUNTU_DEFAULT_PYTHON = {"ubuntu22.04": "3.10", "ubuntu24.04": "3.12"}


def test_gpu_dockerfile_installs_what_its_base_ships():
    """The CUDA image apt-installs a Python its Ubuntu has, pins torch before the project, adds gsplat."""
    import re

    text = (ROOT / "deploy" / "Dockerfile.gpu").read_text()
    base = re.search(r"^FROM\s+(\S+)", text, re.M).group(1)
    ubuntu = next(u for u in UBUNTU_PYTHONS if base.endswith(u))
    apt = " ".join(line for line in text.splitlines() if "apt-get install" in line or "python3" in line)
    named = set(re.findall(r"\bpython(3\.\d+)(?:-dev|-venv)?\b", apt))
    wanted = named or {UBUNTU_DEFAULT_PYTHON[ubuntu]}  # plain python3: the release's own
    assert wanted <= UBUNTU_PYTHONS[ubuntu], f"{base} has no Python {wanted} in its archive"
    pip = [line for line in text.splitlines() if "pip install" in line]
    torch = next(i for i, line in enumerate(pip) if "torch==2.14.1" in line and "torchvision==0.29.1" in line)
    gsplat = next(i for i, line in enumerate(pip) if re.search(r"pip install .*\bgsplat\b", line))
    project = next(i for i, line in enumerate(pip) if re.search(r'pip install "?\.', line))
    assert torch < gsplat < project
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    assert compose["services"]["worker-gpu"]["build"]["dockerfile"] == "deploy/Dockerfile.gpu"


def test_the_wheel_ships_the_dashboard_with_what_its_import_map_loads(tmp_path):
    """A wheel (what `pip install .` and the Docker image install) holds the dashboard, the three.js
    files its import map and modules load and Leaflet's, so that the 3D view and the map work outside a
    dev checkout."""
    import re
    import zipfile

    from servers import build_wheel

    ui = ROOT / "api" / "ui"
    if not (ui / "node_modules" / "three" / "package.json").is_file() and shutil.which("npm") is None:
        pytest.skip("three.js is not installed here and there is no npm to install it")
    names = set(zipfile.ZipFile(build_wheel(tmp_path)).namelist())
    index = (ui / "index.html").read_text()
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', index, re.S).group(1))[
        "imports"
    ]
    three = "api/ui/" + imports["three"].removeprefix("./")
    addons = "api/ui/" + imports["three/addons/"].removeprefix("./")
    used = re.findall(r'from "three/addons/([^"]+)"', (ui / "view3d.js").read_text())
    wanted = {three, "api/ui/index.html", "api/ui/app.js", "api/ui/view3d.js"} | {addons + u for u in used}
    wanted |= {
        three.rsplit("/", 1)[0] + "/" + m
        for m in re.findall(r"from '\./([^']+)'", (ROOT / three).read_text())
    }
    linked = re.findall(r'(?:src|href)="(?:\./)?(node_modules/[^"]+)"', index)  # Leaflet's script and css
    wanted |= {f"api/ui/{f}" for f in linked}
    assert len(linked) >= 2 and "api/ui/node_modules/leaflet/dist/images/marker-icon.png" in names
    assert used and wanted <= names, sorted(wanted - names)
