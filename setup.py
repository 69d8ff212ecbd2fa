"""setuptools hook (the project's metadata is in pyproject.toml): the dashboard's front-end libraries
(three.js for the 3D view, Leaflet for the map, pinned by api/ui/package-lock.json) are installed with
npm before the package is built, so that a wheel, a plain `pip install .` and the Docker image serve
them from the package."""

import shutil
import subprocess
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

UI = Path(__file__).resolve().parent / "api" / "ui"
# what the dashboard loads (api/ui/index.html); pyproject.toml's package data ships them
UI_FILES = (
    "node_modules/leaflet/dist/leaflet.js",
    "node_modules/leaflet/dist/leaflet.css",
    "node_modules/three/build/three.module.js",
    "node_modules/three/build/three.core.js",
    "node_modules/three/examples/jsm/controls/OrbitControls.js",
)


class BuildWithDashboard(build_py):
    def run(self) -> None:
        if not all((UI / f).is_file() for f in UI_FILES):
            npm = shutil.which("npm")
            if npm is None:
                self.warn("no npm: the package is built without three.js and Leaflet (the dashboard says so)")
            else:
                subprocess.run(
                    [npm, "ci", "--prefix", str(UI), "--no-audit", "--no-fund", "--loglevel=error"],
                    check=True,
                )
        super().run()


setup(cmdclass={"build_py": BuildWithDashboard})
