"""The ``anchordp3`` command line. Parses arguments and calls ``pipeline`` or a stage; no logic here."""

from __future__ import annotations

import functools

import typing
from inspect import Parameter, Signature
from inspect import signature as call_signature
import sqlite3
import sys
from pathlib import Path

import typer
from pydantic import BaseModel, ValidationError
from typer._click.exceptions import NoArgsIsHelpError, UsageError  # typer >= 0.29 carries its own click
from typer.core import TyperGroup

from anchordp3.schemas.evaluation import EvalOptions


class _OneLineErrors(TyperGroup):
    """The command line's own argument errors (an out-of-range number, a missing argument, an
    unknown command) in the same one-line form as every other bad input: ``error: ...``, exit 2."""

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except NoArgsIsHelpError as e:
            if not standalone_mode:
                raise
            e.show()
            sys.exit(e.exit_code)
        except typer.TyperException as e:
            if not standalone_mode:
                raise
            typer.echo(f"error: {e.format_message()}", err=True)
            sys.exit(2 if isinstance(e, UsageError) else e.exit_code)
        except typer.Abort:
            if not standalone_mode:
                raise
            typer.echo("Aborted!", err=True)
            sys.exit(1)
        if standalone_mode:
            sys.exit(rv if isinstance(rv, int) else 0)
        return rv


app = typer.Typer(cls=_OneLineErrors, add_completion=False, no_args_is_help=True,
                  help="AnchorDP3 data pipeline: simulated dual-arm data, anchors, policies.")


def _version(value: bool) -> None:
    if value:
        from anchordp3 import __version__

        typer.echo(f"anchordp3 {__version__}")
        raise typer.Exit()


@app.callback()
def _messages(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Also show debug messages."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only warnings and errors (no progress lines)."),
    version: bool = typer.Option(False, "--version", is_eager=True, callback=_version, help="Print the version and exit."),
) -> None:
    """Messages and progress on stderr (``anchordp3.logs``); results on stdout."""
    import logging

    from anchordp3.logs import console

    console(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)


def _one_line(e: Exception) -> str:
    from anchordp3.stages.files import no_space, os_error_line

    if isinstance(e, sqlite3.OperationalError) and no_space(e) is not None:
        return no_space(e)
    if isinstance(e, OSError):
        return os_error_line(e)
    if isinstance(e, ValidationError):
        err = e.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        return f"{loc}: {err['msg']}" if loc else err["msg"]
    return str(e).splitlines()[0] if str(e) else type(e).__name__


def cli_errors(fn=None, *, folders: tuple[str, ...] = (), files: tuple[str, ...] = ()):
    """Bad input becomes a one-line ``error: ...`` on stderr and exit code 2: a bad value, a file
    that is not what it should be, and any OS error while reading or writing (read-only, not a
    directory, no space, permission), naming the path given or the file that failed.

    folders, files: the command's parameters that name where it writes (a folder, a file); each
    given one is checked before any work starts (``files.check_destination``)."""
    if fn is None:
        return functools.partial(cli_errors, folders=folders, files=files)
    signature = call_signature(fn)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from anchordp3.stages.files import check_destination

        try:
            given = signature.bind_partial(*args, **kwargs).arguments
            for name in folders + files:
                if given.get(name) is not None:
                    check_destination(given[name], folder=name in folders)
            return fn(*args, **kwargs)
        except typer.Exit:
            raise
        except (ValueError, ValidationError, OSError, RuntimeError, sqlite3.OperationalError) as e:
            from anchordp3.stages.files import no_space

            if isinstance(e, sqlite3.OperationalError) and no_space(e) is None:
                raise  # a defect, not the disk
            typer.echo(f"error: {_one_line(e)}", err=True)
            raise typer.Exit(2)

    return wrapper


def flags_from(model: type[BaseModel]):
    """Decorator: the command takes one ``--flag`` per field of ``model``, with
    the field's default and its description as help, and receives them validated as one ``model``
    instance in its parameter ``options``. The config is the one source of the flags; a bad value
    is a one-line error naming the flag."""

    def decorate(fn):
        own = [p for name, p in call_signature(fn).parameters.items() if name != "options"]
        fields = model.model_fields
        params = [Parameter(name, Parameter.KEYWORD_ONLY, annotation=_flag_type(f.annotation),
                                    default=typer.Option(None if f.default is None else f.default, f"--{name.replace('_', '-')}", help=f.description))
                  for name, f in fields.items()]

        @functools.wraps(fn)
        def wrapper(**kwargs):
            values = {name: kwargs.pop(name) for name in fields}
            try:
                options = model(**{k: v for k, v in values.items() if v is not None})  # None: the field's default
            except ValidationError as e:
                err = e.errors()[0]
                flag = f"--{str(err['loc'][0]).replace('_', '-')}" if err["loc"] else model.__name__
                raise ValueError(f"{flag}: {err['msg']}") from None
            return fn(options=options, **kwargs)

        wrapper.__signature__ = Signature(own + params)
        wrapper.__annotations__ = {p.name: p.annotation for p in own + params}
        return wrapper

    return decorate


def _flag_type(annotation) -> type:
    """The command-line type of a config field: its one non-None type; a tuple of names is given as
    comma-separated text, and a choice (``Literal``) as text the config checks."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)] or [annotation]
    kind = args[0]
    if kind in (int, float, str, bool, Path):
        return kind
    return str


@app.command()
@cli_errors
def tasks() -> None:
    """List the tasks with their descriptions and step limits."""
    from anchordp3.sim.tasks import TASKS
    from anchordp3.viz.table import text_table

    typer.echo(text_table(["task", "step limit", "description"], [[n, t.step_limit, t.description] for n, t in TASKS.items()]))


@app.command()
@cli_errors(folders=("out",))
def rollout(
    task: str = typer.Argument(..., help="Task name (see `anchordp3 tasks`)."),
    seeds: str = typer.Option("0-9", help="Seeds, e.g. 0-49 or 0,3,7-9."),
    preset: str = typer.Option("randomized", help="Randomization preset: clean or randomized."),
    out: Path = typer.Option(None, help="Folder to save kept episodes into (default: don't save)."),
) -> None:
    """CPU rollouts of the expert (no rendering): a table per seed and the success rate."""
    from anchordp3.pipeline.rollouts import run_rollouts, summarize
    from anchordp3.schemas.episode import parse_seeds
    from anchordp3.schemas.sim import world_config
    from anchordp3.sim.tasks import get_task
    from anchordp3.viz.table import text_table

    get_task(task)
    seed_list = parse_seeds(seeds, "--seeds")
    records = run_rollouts(task, seed_list, world_config(preset), preset, out)
    typer.echo(text_table(["seed", "success", "reason", "steps", "anchors", "seconds"],
                          [[r.seed, r.success, r.reason or "", r.steps, len(r.anchors), r.seconds] for r in records]))
    s = summarize(records)
    typer.echo(f"\n{task} ({preset}): success {s['successes']}/{s['episodes']} = {s['success_rate']:.1%}"
               + (f"; failures: {s['reasons']}" if s["reasons"] else ""))


@app.command()
@cli_errors(files=("out",))
def snapshot(
    task: str = typer.Argument(..., help="Task name (see `anchordp3 tasks`)."),
    seed: int = typer.Option(0, help="Episode seed.", min=0),
    out: Path = typer.Option(Path("views.png"), help="PNG file to write."),
    preset: str = typer.Option("randomized", help="Randomization preset: clean or randomized."),
) -> None:
    """Render the four camera views of a seed's scene into one picture."""
    from anchordp3.schemas.sim import world_config
    from anchordp3.sim.tasks import get_task
    from anchordp3.stages.snapshot import snapshot as take

    get_task(task)
    typer.echo(f"wrote {take(task, seed, world_config(preset), out)}")


def _run_options(stages, workers, address, force, from_stage, keep_outputs):
    from anchordp3.pipeline.runner import RunOptions

    chosen = tuple(x.strip() for x in stages.split(",")) if stages else None
    return RunOptions(stages=chosen, workers=workers, address=address, force=force, from_stage=from_stage,
                      keep_outputs=keep_outputs)


KEEP_OUTPUTS_HELP = "Keep outputs that only older code made (same config) instead of refusing; --force redoes them."


@app.command()
@cli_errors(folders=("run_dir",))
def run(
    config: Path = typer.Argument(..., help="Run config (YAML), e.g. configs/demo.yaml."),
    run_dir: Path = typer.Option(..., "--run-dir", help="Run directory (local, or shared by every cluster node)."),
    stages: str = typer.Option(None, help="Comma-separated stages to run (default: the data stages, then training and evaluation where the config has those sections)."),
    workers: int = typer.Option(None, min=1, help="Actors per stage pool (overrides the config)."),
    address: str = typer.Option(None, help="Ray cluster to join: auto or ray://HOST:PORT (default: $RAY_ADDRESS, else a local Ray)."),
    force: bool = typer.Option(False, "--force", help="Redo the stages a config or code change invalidated."),
    from_stage: str = typer.Option(None, "--from-stage", help="Redo this stage and everything after it."),
    keep_outputs: bool = typer.Option(False, "--keep-outputs", help=KEEP_OUTPUTS_HELP),
) -> None:
    """Run (or resume) a run: the data stages (rollout → anchors → render → features → write), then
    the models and their evaluation where the config has `training:` and `evaluation:`."""
    from anchordp3.pipeline.inspect import run_overview
    from anchordp3.pipeline.runner import run_pipeline
    from anchordp3.schemas.run import load_run_config

    cfg = load_run_config(config)
    run_pipeline(cfg, run_dir, _run_options(stages, workers, address, force, from_stage, keep_outputs))
    typer.echo(run_overview(run_dir))


@app.command()
@cli_errors(folders=("run_dir",))
def stage(
    name: str = typer.Argument(..., help="Stage: rollout, anchors, render, features, write, train-segmenter, train-classifier, train-policy, evaluate or evaluate-train."),
    run_dir: Path = typer.Option(..., "--run-dir", help="Run directory holding config.yaml (from an earlier `run`)."),
    config: Path = typer.Option(None, help="Run config (default: the run directory's config.yaml)."),
    workers: int = typer.Option(None, min=1, help="Actors in the pool (overrides the config)."),
    address: str = typer.Option(None, help="Ray cluster to join: auto or ray://HOST:PORT."),
    force: bool = typer.Option(False, "--force", help="Redo the stage if a config or code change invalidated it."),
    keep_outputs: bool = typer.Option(False, "--keep-outputs", help=KEEP_OUTPUTS_HELP),
) -> None:
    """Run one stage alone; its input stages must be complete."""
    from anchordp3.pipeline.inspect import run_overview
    from anchordp3.pipeline.products import GRAPH
    from anchordp3.pipeline.runner import CONFIG_FILE, run_pipeline
    from anchordp3.schemas.run import load_run_config

    if name not in GRAPH.names:
        raise ValueError(f"stage {name!r}: unknown; choose from {', '.join(GRAPH.names)}")
    cfg = load_run_config(config or run_dir / CONFIG_FILE)
    run_pipeline(cfg, run_dir, _run_options(name, workers, address, force, None, keep_outputs))
    typer.echo(run_overview(run_dir))


@app.command()
@cli_errors(files=("out",))
def show(
    path: Path = typer.Argument(..., help="A run directory, a rendered-frames file (render/frames/…npz) or a features file."),
    frame: int = typer.Option(0, help="Frame index within the episode's file."),
    episode: str = typer.Option(None, help="In a run directory: the episode as TASK/SEED (default: the first rendered one)."),
    out: Path = typer.Option(Path("frame.png"), help="PNG file to write."),
) -> None:
    """Picture of one frame: camera images, critical masks, the fused cloud by colour and by label."""
    from anchordp3.pipeline.show import show_frame

    typer.echo(f"wrote {show_frame(path, out, frame, episode)}")


@app.command()
@cli_errors(folders=("run_dir",))
def demo(
    run_dir: Path = typer.Option(Path("runs/demo"), "--run-dir", help="Run directory (re-running resumes it)."),
    seeds: str = typer.Option(None, help="Seeds per task (default: the embedded config's)."),
    address: str = typer.Option(None, help="Ray cluster to join (default: $RAY_ADDRESS, else a local Ray)."),
    episodes: int = typer.Option(1, "--episodes", min=1, help="Evaluation episodes per task."),
    max_decisions: int = typer.Option(8, "--max-decisions", min=1, help="Cap on policy calls per evaluation episode of the demo's own policy."),
    data_only: bool = typer.Option(False, "--data-only", help="Stop after the data stages."),
) -> None:
    """The whole system on the embedded tiny default (configs/demo.yaml): data, training,
    closed-loop evaluation and its success table, in minutes."""
    from anchordp3.pipeline.demo import DemoOptions, demo_config, run_demo

    opts = DemoOptions(episodes=episodes, max_decisions=max_decisions, train=not data_only, address=address)
    run_demo(run_dir, demo_config(seeds), opts=opts)


@app.command()
@cli_errors
def status(
    run_dir: Path = typer.Argument(..., help="Run directory."),
) -> None:
    """One line per data stage, trained model and evaluation: done/failed/planned, complete, compute seconds, fingerprint, stale."""
    from anchordp3.pipeline.inspect import product_status, run_status, status_table

    typer.echo(status_table(run_status(run_dir) + product_status(run_dir)))


@app.command()
@cli_errors
def inspect(
    run_dir: Path = typer.Argument(..., help="Run directory."),
    stage: str = typer.Argument(None, help="A data stage (rollout, anchors, render, features, write); default: all, as a table."),
    item: str = typer.Option(None, "--item", help="One item's whole record, e.g. place_mouse/000003 or shard/00000 (in STAGE, or in every stage)."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable: the statuses, the manifest or the record(s) as JSON."),
    limit: int = typer.Option(50, min=0, help="Items listed at most in a stage's table (0: all)."),
) -> None:
    """A run's stages, a stage's manifest (counts, fingerprint, slowest items, failure reasons, items), or one item."""
    from anchordp3.pipeline.inspect import inspect_json, inspect_text

    typer.echo(inspect_json(run_dir, stage, item) if as_json else inspect_text(run_dir, stage, item, limit))


@app.command()
def verify(
    run_dir: Path = typer.Argument(..., help="Run directory."),
    repair: bool = typer.Option(False, "--repair", help="Forget the broken items, resume the run to redo exactly them, verify again."),
    address: str = typer.Option(None, help="With --repair: Ray cluster to join (auto or ray://HOST:PORT; default: $RAY_ADDRESS, else a local Ray)."),
) -> None:
    """Check every done item's output against its recorded checksum; exit 1 when any is missing or corrupt."""
    raise typer.Exit(_verify(run_dir, repair, address, writes=run_dir if repair else None))


@cli_errors(folders=("writes",))
def _verify(run_dir: Path, repair: bool, address: str | None, writes: Path | None) -> int:
    # the exit code is raised outside ``cli_errors``: typer.Exit is a RuntimeError, which it would catch;
    # ``writes``: the run directory when repairing (checked as a destination), else None (verify only reads)
    from anchordp3.pipeline.verify import repair_run, verify_run

    if not repair:
        report = verify_run(run_dir)
        typer.echo(report.text())
        return 0 if report.ok else 1
    before, after = repair_run(run_dir, address)
    if not before.ok:
        typer.echo(before.text() + "\n\nafter repair:")
    typer.echo(after.text())
    return 0 if after.ok else 1


config_app = typer.Typer(no_args_is_help=True, help="Run configs: show resolved, validate, JSON schema.")
app.add_typer(config_app, name="config")


@config_app.command("show")
@cli_errors
def config_show(config: Path = typer.Argument(..., help="Run config (YAML).")) -> None:
    """Print the resolved config (every default filled in) as YAML."""
    from anchordp3.pipeline.inspect import resolved_config_yaml

    typer.echo(resolved_config_yaml(config), nl=False)


@config_app.command("validate")
@cli_errors
def config_validate(config: Path = typer.Argument(..., help="Run config (YAML).")) -> None:
    """Print OK, or a one-line error naming the field (exit 2)."""
    from anchordp3.pipeline.inspect import config_summary

    typer.echo(config_summary(config))


@config_app.command("schema")
@cli_errors
def config_schema(what: str = typer.Option("run", "--what", help="run: the run config; manifest: a stage manifest.")) -> None:
    """Print the JSON schema of the run config or of a stage manifest."""
    from anchordp3.pipeline.inspect import json_schema

    typer.echo(json_schema(what))


train_app = typer.Typer(no_args_is_help=True, help="Train the models on a run's dataset: segmenter, classifier, policy, or all.")
app.add_typer(train_app, name="train")


def _train(models: list[str], run_dir: Path, config: Path | None, preset: str, steps: int | None, device: str | None,
           force: bool, keep_outputs: bool) -> None:
    from anchordp3.pipeline.targets import train_models, training_summary
    from anchordp3.pipeline.training import load_training_config

    cfg = load_training_config(config, preset, steps, device)
    results = train_models(run_dir, models, cfg, force=force, keep_outputs=keep_outputs)
    typer.echo(training_summary(results))


def _train_command(models: list[str], doc: str):
    @cli_errors(folders=("run_dir",))
    def command(
        run_dir: Path = typer.Option(..., "--run-dir", help="Run directory with a complete dataset (from `anchordp3 run`)."),
        config: Path = typer.Option(None, "--config", help="Training config YAML: any subset of the training fields, over the preset."),
        preset: str = typer.Option("cpu", "--preset", help="Base sizes: cpu (minutes on a laptop) or report (AnchorDP3 scale, GPU)."),
        steps: int = typer.Option(None, "--steps", min=1, help="Optimizer steps of each model (overrides epochs)."),
        device: str = typer.Option(None, "--device", help="auto (CUDA when present), cpu or cuda (overrides the config)."),
        force: bool = typer.Option(False, "--force", help="Retrain a model whose config, code or upstream changed."),
        keep_outputs: bool = typer.Option(False, "--keep-outputs", help="Keep a model that only older code trained (same settings and data) instead of refusing."),
    ) -> None:
        _train(models, run_dir, config, preset, steps, device, force, keep_outputs)

    command.__doc__ = doc
    return command


train_app.command("segmenter")(_train_command(["segmenter"], "Train the PointNet++ segmenter (points -> critical-object probability)."))
train_app.command("classifier")(_train_command(["classifier"], "Fine-tune the instruction classifier (text -> task)."))
train_app.command("policy")(_train_command(["policy"], "Train the anchor diffusion policy (frame -> next anchors)."))
train_app.command("all")(_train_command(["segmenter", "classifier", "policy"], "Train the segmenter, the classifier, then the policy."))



@app.command("eval")
@cli_errors(folders=("out",))
@flags_from(EvalOptions)
def eval_(
    run_dir: Path = typer.Option(None, "--run-dir", help="Run directory with trained models (from `anchordp3 train all`)."),
    options: EvalOptions = None,
) -> None:
    """Closed-loop evaluation: success rate per task with 95 % intervals, table, chart, report in <run>/eval (or --out)."""
    from anchordp3.pipeline.evaluation import evaluation_summary
    from anchordp3.pipeline.targets import evaluation_folder, run_evaluation

    records = run_evaluation(run_dir, options)
    typer.echo(evaluation_summary(records))
    typer.echo(f"report: {evaluation_folder(run_dir, options) / 'report.md'}")


experiment_app = typer.Typer(no_args_is_help=True, help="Experiments that compare data recipes end to end.")
app.add_typer(experiment_app, name="experiment")


@experiment_app.command("anchors-vs-dense")
@cli_errors(folders=("out",))
def anchors_vs_dense(
    config: Path = typer.Argument(Path("configs/experiment.yaml"), help="Experiment config (YAML): run, training, eval."),
    out: Path = typer.Option(Path("runs/anchors-vs-dense"), "--out", help="Experiment folder (re-running resumes it)."),
    address: str = typer.Option(None, "--address", help="Ray cluster to join (default: $RAY_ADDRESS, else a local Ray)."),
) -> None:
    """Sparse anchors versus dense DP3-style frames at the same render budget: data, training and
    closed-loop evaluation of both; trajectories per budget, success per task, wall time per phase."""
    from anchordp3.pipeline.experiment import experiment_report, run_experiment
    from anchordp3.schemas.experiment import load_experiment_config

    results = run_experiment(out, load_experiment_config(config), address=address)
    typer.echo(experiment_report(results))
    typer.echo(f"report: {out / 'report.md'}")


@experiment_app.command("recipe")
@cli_errors(folders=("out",))
def recipe(
    config: Path = typer.Argument(Path("configs/recipe.yaml"), help="Recipe config (YAML): run, training, eval."),
    out: Path = typer.Option(Path("runs/recipe"), "--out", help="Recipe folder (re-running resumes it)."),
    address: str = typer.Option(None, "--address", help="Ray cluster to join (default: $RAY_ADDRESS, else a local Ray)."),
    keep_outputs: bool = typer.Option(False, "--keep-outputs", help="Resume data that older code made (same config) instead of refusing."),
    force: bool = typer.Option(False, "--force", help="Redo the stages and models a config or code change invalidated."),
    from_stage: str = typer.Option(None, "--from-stage", help="Redo this stage and everything after it (more seeds: --from-stage write keeps every episode made and adds the new ones)."),
) -> None:
    """The best known recipe end to end: data, the three models, closed-loop evaluation on unseen
    seeds and on training seeds; report with success per task, first-anchor errors and wall times."""
    from anchordp3.pipeline.recipe import recipe_report, run_recipe
    from anchordp3.schemas.recipe import load_recipe_config

    results = run_recipe(out, load_recipe_config(config), address=address,
                         keep_outputs=keep_outputs, force=force, from_stage=from_stage)
    typer.echo(recipe_report(results))
    typer.echo(f"report: {out / 'report.md'}")


export_app = typer.Typer(no_args_is_help=True, help="Take models or data out of a run.")
app.add_typer(export_app, name="export")


@export_app.command("pretrained")
@cli_errors(folders=("dest",))
def export_pretrained(
    run_dir: Path = typer.Argument(..., help="Run directory with trained models (e.g. a recipe's run/), or a shipped models folder to ship again."),
    dest: Path = typer.Option(None, "--dest", help="Destination folder (default: the package's pretrained/, what `--models pretrained` loads)."),
    command: str = typer.Option("", "--command", help="The command that made the models, recorded beside them."),
    ddim_steps: int = typer.Option(None, "--ddim-steps", min=1, max=100, help="DDIM steps per decision of the shipped policy (default: the ones it was trained with)."),
) -> None:
    """Ship a run's three models as a self-contained models folder (EMA policy weights, the
    classifier's changed tensors only), with their manifests, training config and run config."""
    from anchordp3.pipeline.shipping import ship_models

    typer.echo(ship_models(run_dir, dest, command, ddim_steps))


@export_app.command("lerobot")
@cli_errors(folders=("out",))
def export_lerobot_cmd(
    run_dir: Path = typer.Argument(..., help="Run directory with a complete dataset (from `anchordp3 run`)."),
    out: Path = typer.Argument(..., help="LeRobot dataset folder to create (must not exist)."),
    images: bool = typer.Option(True, "--images/--no-images", help="Include the kept camera images (when the run kept them)."),
) -> None:
    """The run's dataset as a LeRobotDataset (v3.0 layout): one frame per keyframe, action = the
    next anchor, the point cloud, and each camera's images when the run kept them."""
    from anchordp3.pipeline.exports import export_lerobot

    typer.echo(export_lerobot(run_dir, out, images=images).line())


@export_app.command("dp3")
@cli_errors(folders=("out",))
def export_dp3_cmd(
    run_dir: Path = typer.Argument(..., help="Run directory with a complete dataset (from `anchordp3 run`)."),
    out: Path = typer.Argument(..., help="DP3 zarr folder to create, e.g. OUT.zarr (must not exist)."),
) -> None:
    """The run's dataset in DP3's zarr layout (format 2): data/point_cloud (T, N, 6), data/state,
    data/action (the next anchor), meta/episode_ends."""
    from anchordp3.pipeline.exports import export_dp3

    typer.echo(export_dp3(run_dir, out).line())


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
