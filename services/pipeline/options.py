"""Options of a pipeline job: one validated pydantic model for the API, the CLI and the workers.

The API lists them at `GET /options` (option_specs) and validates `POST /projects/{id}/jobs` bodies with
JobOptions; the workers read `Job.options` back with `JobOptions.model_validate(job.options)`.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.pipeline.registry import DEFAULT_STAGES, GROUND_STAGES, STAGES

Stage = Literal[STAGES]  # the registry's stage names, in pipeline order


class JobOptions(BaseModel):
    """Every knob of a job; unknown fields are rejected so that a typo never passes silently, and so
    are NaN and infinities."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    stages: list[Stage] = Field(
        default_factory=lambda: list(DEFAULT_STAGES),
        min_length=1,
        description="Pipeline stages to run (kept in pipeline order); default: all but splat_all (a 3DGS"
        " on all images of the combined model, aerial and ground: add it to train one)",
    )
    sfm_features: Literal["sift", "aliked"] = Field(
        "sift", description="Local features of the aerial structure-from-motion"
    )
    matcher: Literal["aliked-lightglue", "sift"] = Field(
        "aliked-lightglue", description="Matcher between rendered views and the aerial/ground images"
    )
    view_planner: Literal["paper", "ground-aware", "both"] = Field(
        "both",
        description="How intermediate viewpoints are chosen between aerial and ground cameras: the paper's"
        " lowered aerial cameras, views placed above and behind the ground cameras, or both (measured best"
        " with sharp views: 1171 GT-correct matches and 11/15 ground images, 13/15 with four views per ground"
        " image, against 835 and 2/15 for paper)",
    )
    views_per_ground_image: int = Field(
        4, ge=1, le=16, description="Intermediate views rendered per ground image"
    )
    splat_steps: int = Field(7000, ge=100, le=200_000, description="3DGS training iterations")
    splat_time_budget_s: float | None = Field(
        None,
        ge=1,
        le=7 * 24 * 3600,
        description="Seconds of 3DGS training at most: fewer than splat_steps iterations when the machine is"
        " slower (the run's length follows the pace of its last iterations); null: all of them",
    )
    block_steps: int = Field(
        0,
        ge=0,
        le=200_000,
        description="3DGS training steps of each block of the scene the intermediate views see, on crops of"
        " the aerial images at their source resolution (stage train_blocks); 0: none, the views render from"
        " the whole-scene 3DGS (the default: on 2 CPU cores 11 blocks of 200 steps took 12 minutes for"
        " 1.13x the matchable view pixels and no more ground images registered, docs/measurements.md)",
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
        1600, ge=64, le=8192, description="Aerial images are downscaled to this width for 3DGS training"
    )
    max_keypoints: int = Field(4096, ge=64, le=65_536, description="Keypoints per image for matching")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Random seed (view planning, training)")
    out_crs: str | None = Field(
        None,
        max_length=64,
        description="CRS of the georeferenced outputs (camera lists, GIS files), e.g. EPSG:32633; default: "
        "the project's, else the POS's (GIS files: the site's UTM zone when that is geographic)",
    )

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
    """One entry per option: name, type, default, help, and choices/minimum/maximum where they apply."""
    schema = JobOptions.model_json_schema()
    defaults = JobOptions().model_dump(mode="json")
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
