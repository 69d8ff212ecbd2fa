"""What a finished job gave its user: images registered per set, and the warnings that make a
"succeeded" job one to look at (ground images that did not register, aerial images left out).

Computed once from the stage summaries when the job succeeds (workers), stored in the job's metrics
under "outcome", and shown by the API's job status, its event stream and the webhook payload.
"""

from __future__ import annotations

from typing import Any


def _counts(summary: dict[str, Any]) -> tuple[dict[str, int], dict[str, int]]:
    """(registered, total) per set of a stage summary holding num_registered / num_images, or "NRI"
    strings ("12/15")."""
    if "num_registered" in summary and "num_images" in summary:
        return dict(summary["num_registered"]), dict(summary["num_images"])
    reg, tot = {}, {}
    nri = summary.get("NRI") or {}
    if isinstance(nri, str):
        nri = {"aerial": nri}
    for s, text in nri.items():
        try:
            a, b = (int(v) for v in str(text).split("/"))
        except ValueError:
            continue
        reg[s], tot[s] = a, b
    return reg, tot


def job_outcome(metrics: dict[str, Any]) -> dict[str, Any]:
    """{"registered": {set: n}, "images": {set: n}, "result": "ok" | "warnings", "warnings": [...],
    "causes": {cause: n}} from the stage summaries (the combined reconstruction's where it ran, else the
    aerial SfM's); `causes` counts the named causes of the ground images left out (the combined
    reconstruction's report: services.sfm.combined.report.CAUSES)."""
    source = next((s for s in ("combined_sfm", "aerial_sfm") if s in metrics), None)
    reg, tot = _counts(metrics.get(source) or {}) if source else ({}, {})
    warnings = []
    for s in ("ground", "aerial"):
        if s not in tot:
            continue
        missing = tot[s] - reg.get(s, 0)
        if s == "ground" and reg.get(s, 0) == 0 and tot[s] > 0:
            warnings.append(f"no ground image registered (0 of {tot[s]})")
        elif missing > 0:
            warnings.append(f"{missing} of {tot[s]} {s} images not registered")
    return {
        "from_stage": source,
        "registered": reg,
        "images": tot,
        "result": "warnings" if warnings else "ok",
        "warnings": warnings,
        "causes": dict((metrics.get(source) or {}).get("causes") or {}) if source == "combined_sfm" else {},
    }
