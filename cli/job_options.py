"""The job options of `midview run` and `midview demo`, generated from services.pipeline.JobOptions: one
flag per option (its name with dashes), its help the field's description with each profile's default.
A flag not given leaves the option to the job's profile (--profile, default cpu)."""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from typing import Any

import typer

from services.pipeline import PROFILES, JobOptions

# flags kept under their earlier names as well
FLAG_ALIASES: dict[str, tuple[str, ...]] = {"splat_time_budget_s": ("--splat-time-budget",)}
NOT_FLAGS = frozenset({"stages"})  # the commands take --stages and --splat-all themselves
ZERO_IS_NONE = frozenset({"splat_time_budget_s"})  # 0 on the command line: no limit (null)


def _base_type(annotation: Any) -> tuple[type, list[Any] | None]:
    """(the CLI type, choices) of a field's annotation: Literal -> str with its choices; X | None -> X."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if typing.get_origin(annotation) is typing.Literal:
        return str, list(typing.get_args(annotation))
    if len(args) == 1:  # X | None
        return _base_type(args[0])
    return (annotation if isinstance(annotation, type) else str), None


def _help(name: str, description: str, choices: list[Any] | None) -> str:
    defaults = {p: values.get(name, JobOptions.model_fields[name].default) for p, values in PROFILES.items()}
    if len(set(map(str, defaults.values()))) == 1:
        shown = f"default {next(iter(defaults.values()))}"
    else:
        shown = "defaults " + ", ".join(f"{p} {v}" for p, v in defaults.items())
    listed = f" [{'|'.join(map(str, choices))}]" if choices else ""
    zero = "; 0: none" if name in ZERO_IS_NONE else ""
    return f"{description}{listed} ({shown}{zero})"


def option_parameters(exclude: frozenset[str] = frozenset()) -> list[inspect.Parameter]:
    """One keyword-only typer parameter per JobOptions field (default None: the profile's value)."""
    params = []
    for name, field in JobOptions.model_fields.items():
        if name in NOT_FLAGS or name in exclude:
            continue
        kind, choices = _base_type(field.annotation)
        flag = "--" + name.replace("_", "-")
        option = typer.Option(
            None, flag, *FLAG_ALIASES.get(name, ()), help=_help(name, field.description or "", choices)
        )
        params.append(
            inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option, annotation=kind | None)
        )
    return params


def explain(error: Any) -> str:
    """A pydantic ValidationError of JobOptions as the flags' messages ("--splat-steps: Input should...")."""
    lines = []
    for e in error.errors():
        name = str(e["loc"][0]) if e.get("loc") else ""
        flag = "--" + name.replace("_", "-") if name else "options"
        lines.append(f"{flag}: {e['msg']}")
    return "; ".join(lines)


def with_job_options(
    exclude: frozenset[str] = frozenset(),
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """A typer command taking every job option as a flag; the command receives those given as
    `job_options` (a dict for JobOptions), the rest are left to the profile."""

    def decorate(command: Callable[..., Any]) -> Callable[..., Any]:
        generated = option_parameters(exclude)
        names = [p.name for p in generated]
        own = [p for p in inspect.signature(command).parameters.values() if p.name != "job_options"]

        @functools.wraps(command)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            given = {n: kwargs.pop(n) for n in names if n in kwargs}
            options = {
                k: (None if k in ZERO_IS_NONE and v == 0 else v) for k, v in given.items() if v is not None
            }
            return command(*args, job_options=options, **kwargs)

        wrapper.__signature__ = inspect.Signature([*own, *generated])  # type: ignore[attr-defined]
        return wrapper

    return decorate
