"""Conf dicts of the pipeline steps (each step's `confs`, hloc style): merging an override into a conf,
and `key=value` overrides from the command line or a job's settings."""

from __future__ import annotations

import copy
import json
from typing import Any


def merge_conf(base: dict, over: dict | None) -> dict:
    """A deep copy of base with over merged in: nested dicts merge, anything else replaces."""
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        out[k] = merge_conf(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _parse_value(text: str) -> Any:
    """JSON (numbers, true/false/null, lists, quoted strings), else a Python float or bool word, else the
    text itself."""
    try:
        return json.loads(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        pass
    words = {"true": True, "false": False, "none": None}
    return words.get(text.strip().lower(), text)


def parse_overrides(items: list[str], base: dict) -> dict:
    """`key=value` strings (dotted keys for nested entries: "strategy.refine_every=100",
    "lr.means=3e-4") -> a nested override of `base` (merge it with `merge_conf`).

    Keys must exist in `base`; a value must fit the kind of the one it replaces (ints stay ints, a number
    for a float, a number or null for null, a list of the same length for a list, of any length for an
    empty one, no group replaced by a value). Raises ValueError with the reason."""
    over: dict = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"{item!r}: expected key=value, e.g. strategy.refine_every=100")
        *path, last = key.split(".")
        cur, dst = base, over
        for i, k in enumerate(path):
            if not isinstance(cur.get(k), dict):
                raise ValueError(f"{key}: unknown key {'.'.join(path[: i + 1])!r}")
            cur, dst = cur[k], dst.setdefault(k, {})
        if last not in cur:
            known = ", ".join(sorted(cur))
            raise ValueError(f"{key}: unknown key {last!r} (known here: {known})")
        old, value = cur[last], _parse_value(text)
        if isinstance(old, dict):
            raise ValueError(f"{key} is a group: set its entries, e.g. {key}.{next(iter(old), 'x')}=...")
        if isinstance(old, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{key}: expected true or false, got {text!r}")
        elif isinstance(old, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{key}: expected an integer, got {text!r}")
        elif isinstance(old, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{key}: expected a number, got {text!r}")
            value = float(value)
        elif old is None:  # the confs' optional entries are numbers
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
                raise ValueError(f"{key}: expected a number or null, got {text!r}")
        elif isinstance(old, list) and not (isinstance(value, list) and (len(value) == len(old) or not old)):
            raise ValueError(f"{key}: expected a list of {len(old)} values, e.g. {json.dumps(old)}")
        dst[last] = value
    return over
