"""The `midview` command line. Heavy imports live inside the commands so `--help` stays fast."""

from __future__ import annotations

import typer

from cli import admin, client, evaluate, match, pos, run, serve, sfm, splat, synth, worker
from shared.config import get_settings
from shared.logging import setup_logging

app = typer.Typer(
    name="midview",
    help="Register aerial (UAV) and ground images through rendered intermediate views.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(
    log_level: str = typer.Option(None, help="DEBUG, INFO, WARNING or ERROR (default: MIDVIEW_LOG_LEVEL)"),
) -> None:
    settings = get_settings()
    setup_logging(log_level or settings.log_level, settings.log_json)


app.command("synth")(synth.synth)
app.command("sfm")(sfm.sfm)
app.command("run")(run.run)
app.command("demo")(run.demo)
app.command("serve")(serve.serve)
app.command("worker")(worker.worker)
app.command("submit")(client.submit)
app.command("jobs")(client.jobs)
app.command("download")(client.download)
app.add_typer(client.campaign_app, name="campaign")
app.add_typer(admin.app, name="admin")
app.add_typer(evaluate.app, name="eval")
app.add_typer(match.app, name="match")
app.add_typer(pos.app, name="pos")
app.add_typer(splat.app, name="splat")

if __name__ == "__main__":
    app()
