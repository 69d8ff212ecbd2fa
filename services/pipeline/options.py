"""Options of a pipeline job: one validated pydantic model for the API, the CLI and the workers.

The API lists them at `GET /options` (option_specs) and validates `POST /projects/{id}/jobs` bodies with
JobOptions; the workers read `Job.options` back with `JobOptions.model_validate(job.options)`.

A job's defaults come from its **profile** (PROFILES): `cpu`, the recipe measured on 2 CPU cores that the
demo and the benches run (docs/measurements.md), and `gpu`, the paper's scale for gsplat workers. An
option given explicitly wins over its profile's value. The API picks the profile from what the workers
offer when a request names none (shared.dispatch.offered_profile); `midview run` and `midview demo` use
`cpu` unless told otherwise.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from services.pipeline.registry import DEFAULT_STAGES, GROUND_STAGES, STAGES

Stage = Literal[STAGES]  # type: ignore[valid-type]  # the registry's stage names, in pipeline order
Profile = Literal["cpu", "gpu"]

# each profile's values of the options it sets; the others have one default for every profile
PROFILES: dict[str, dict[str, Any]] = {
    "cpu": {
        "sfm_max_image_size": 1024,
        "sfm_max_features": 4096,
        "sfm_neighbors": 12,
        "splat_max_gaussians": 120_000,
        "view_planner": "paper",
        "views_per_ground_image": 2,
        "splat_steps": 3000,
        "splat_time_budget_s": 300.0,
        "splat_epochs": 60.0,
        "splat_max_width": 400,
        "max_keypoints": 1024,
    },
    "gpu": {
        "sfm_max_image_size": 1600,
        "sfm_max_features": 8192,
        "sfm_neighbors": 20,
        "splat_max_gaussians": 0,
        "view_planner": "both",
        "views_per_ground_image": 4,
        "splat_steps": 7000,
        "splat_time_budget_s": None,
        "splat_epochs": None,
        "splat_max_width": 1600,
        "max_keypoints": 4096,
    },
}
DEFAULT_PROFILE: Profile = "cpu"
PROFILE_HELP = {
    "cpu": "the recipe measured on 2 CPU cores (the demo's and the benches'): minutes per stage",
    "gpu": "the paper's scale for workers with a CUDA GPU (gsplat): sharper 3DGS, more views and keypoints",
}
CPU = PROFILES[DEFAULT_PROFILE]


class JobOptions(BaseModel):
    """Every knob of a job; unknown fields are rejected so that a typo never passes silently, and so
    are NaN and infinities."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    profile: Profile = Field(
        DEFAULT_PROFILE,
        description="Whose defaults the options not given take: cpu (the recipe measured on 2 CPU cores) or "
        "gpu (the paper's scale, gsplat workers); the service picks it from its workers when not given",
    )
    stages: list[Stage] = Field(
        default_factory=lambda: list(DEFAULT_STAGES),
        min_length=1,
        description="Pipeline stages to run (kept in pipeline order); default: all but splat_all (a 3DGS"
        " on all images of the combined model, aerial and ground: add it to train one)",
    )
    sfm_features: Literal["sift", "aliked"] = Field(
        "sift", description="Local features of the aerial structure-from-motion"
    )
    sfm_max_image_size: int = Field(
        CPU["sfm_max_image_size"],
        ge=256,
        le=16_384,
        description="Aerial images are downscaled to this size (longest side, pixels) for the SfM's SIFT"
        " features; their keypoints are kept at full resolution",
    )
    sfm_max_features: int = Field(
        CPU["sfm_max_features"], ge=256, le=65_536, description="SIFT features per aerial image at most"
    )
    sfm_neighbors: int = Field(
        CPU["sfm_neighbors"],
        ge=2,
        le=500,
        description="Aerial images each aerial image is matched with, its nearest by POS, when the survey"
        " is too large to match every pair and has no footprints (no POS attitude or terrain height)",
    )
    matcher: Literal["aliked-lightglue", "sift"] = Field(
        "aliked-lightglue", description="Matcher between rendered views and the aerial/ground images"
    )
    view_planner: Literal["paper", "ground-aware", "both"] = Field(
        CPU["view_planner"],
        description="How intermediate viewpoints are chosen between aerial and ground cameras: the paper's"
        " lowered aerial cameras, views placed above and behind the ground cameras, or both (twice the"
        " views)",
    )
    views_per_ground_image: int = Field(
        CPU["views_per_ground_image"], ge=1, le=16, description="Intermediate views rendered per ground image"
    )
    splat_steps: int = Field(CPU["splat_steps"], ge=100, le=200_000, description="3DGS training iterations")
    splat_max_gaussians: int = Field(
        CPU["splat_max_gaussians"],
        ge=0,
        le=100_000_000,
        description="Gaussians of the 3DGS at most (its densification stops growing there); 0: no cap",
    )
    splat_time_budget_s: float | None = Field(
        CPU["splat_time_budget_s"],
        ge=1,
        le=7 * 24 * 3600,
        description="Seconds of 3DGS training at most: fewer than splat_steps iterations when the machine is"
        " slower (the run's length follows the pace of its last iterations); null: all of them",
    )
    splat_epochs: float | None = Field(
        CPU["splat_epochs"],
        gt=0,
        le=100_000,
        description="Passes over the aerial training images at most: a small survey trains fewer than"
        " splat_steps iterations (splat_epochs x its training images), its schedule scaled with them; null:"
        " splat_steps",
    )
    block_steps: int = Field(
        0,
        ge=0,
        le=200_000,
        description="3DGS training steps of each block of the scene the intermediate views see, on crops of"
        " the aerial images at their source resolution (stage train_blocks); 0: none, the views render from"
        " the whole-scene 3DGS",
    )
    block_px: int = Field(
        640,
        ge=64,
        le=8192,
        description="Size of a block of train_blocks, in pixels of the aerial images at their source"
        " resolution: a block's cell on the ground spans this many pixels, so that a crop of about this size"
        " sees it",
    )
    splat_max_width: int = Field(
        CPU["splat_max_width"],
        ge=64,
        le=8192,
        description="Aerial images are downscaled to this width for 3DGS training",
    )
    max_keypoints: int = Field(
        CPU["max_keypoints"], ge=64, le=65_536, description="Keypoints per image for matching"
    )
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Random seed (view planning, training)")
    out_crs: str | None = Field(
        None,
        max_length=64,
        description="CRS of the georeferenced outputs (camera lists, GIS files), e.g. EPSG:32633; default: "
        "the project's, else the POS's (GIS files: the site's UTM zone when that is geographic)",
    )

    @model_validator(mode="after")
    def _profile_defaults(self) -> JobOptions:
        """The options not given take the profile's values (they stay out of model_fields_set)."""
        for name, value in PROFILES[self.profile].items():
            if name not in self.model_fields_set:
                object.__setattr__(self, name, value)
        return self

    def given(self) -> dict[str, Any]:
        """The options given explicitly (JSON values): what a request asked for, before the profile."""
        return self.model_dump(mode="json", include=set(self.model_fields_set))

    def with_profile(self, profile: str) -> JobOptions:
        """The same explicit options with another profile's defaults."""
        return JobOptions.model_validate({**self.given(), "profile": profile})

    @field_validator("out_crs")
    @classmethod
    def _known_crs(cls, value: str | None) -> str | None:
        if value is None:
            return None
        from pyproj import CRS
        from pyproj.exceptions import CRSError

        try:
            CRS.from_user_input(value)
        except CRSError as e:
            raise ValueError(f"unknown CRS {value!r}: {e}") from None
        return value

    @field_validator("stages")
    @classmethod
    def _pipeline_order(cls, value: list[str]) -> list[str]:
        """No repeats; pipeline order whatever order was given."""
        if len(set(value)) != len(value):
            raise ValueError("stages must not repeat")
        return sorted(value, key=STAGES.index)

    def needs_ground(self) -> bool:
        """Whether any selected stage works on ground images."""
        return any(s in GROUND_STAGES for s in self.stages)

    def stages_from(self, from_stage: str | None) -> list[str]:
        """The selected stages from from_stage on (all of them for None); ValueError if not selected."""
        if from_stage is None:
            return list(self.stages)
        if from_stage not in self.stages:
            raise ValueError(f"stage {from_stage!r} is not among this job's stages {self.stages}")
        return self.stages[self.stages.index(from_stage) :]


def _type_name(schema: dict[str, Any]) -> str:
    if schema.get("type") == "array":
        return f"list[{_type_name(schema.get('items', {}))}]"
    return str(schema.get("type", "string" if "enum" in schema else "any"))


def option_specs() -> list[dict[str, Any]]:
    """One entry per option: name, type, default (the default profile's), defaults (per profile), help,
    and choices/minimum/maximum where they apply."""
    schema = JobOptions.model_json_schema()
    by_profile = {p: JobOptions.model_validate({"profile": p}).model_dump(mode="json") for p in PROFILES}
    defaults = by_profile[DEFAULT_PROFILE]
    out = []
    for name, prop in schema["properties"].items():
        kinds = [b for b in prop.get("anyOf", [prop]) if b.get("type") != "null"]
        nullable = len(kinds) < len(prop.get("anyOf", [prop]))
        if len(kinds) == 1:  # an optional value: its kind's type and bounds
            prop = {**kinds[0], **{k: v for k, v in prop.items() if k != "anyOf"}}
        spec: dict[str, Any] = {
            "name": name,
            "type": _type_name(prop) + (" | null" if nullable else ""),
            "default": defaults[name],
            "defaults": {p: values[name] for p, values in by_profile.items()},
            "help": prop.get("description", ""),
        }
        choices = prop.get("enum") or prop.get("items", {}).get("enum")
        if choices:
            spec["choices"] = list(choices)
        for k in ("minimum", "maximum"):
            if k in prop:
                spec[k] = prop[k]
        out.append(spec)
    return out
