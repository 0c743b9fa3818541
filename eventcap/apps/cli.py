"""The ``eventcap`` command: run pipelines (Hydra), list stages, inspect and clean the cache.

    eventcap run [hydra overrides]       run the configured pipeline; -m for sweeps; --help: the groups, the pipeline's
                                         nodes and their keys; --cfg job: the composed config
    eventcap simulate [key=value ...]    write a synthetic recording (motion=karate_kick duration_s=1 seed=0; run
                                         takes the source's keys bare too)
    eventcap stages [--kind K]           installed stages with one-line descriptions (imports no implementation)
    eventcap cache ls | explain KEY | gc inspect and clean the stage cache
    eventcap preview FILE                PNG of frames (or images from events), events and the ground-truth skeleton,
                                         at the most active moment, into the current folder (or --out); any readable
                                         format; says what it read
    eventcap benchmark [overrides]       Table 1 / Fig. 7 on synthetic captures: methods x motions x seeds, one cache
                                         (benchmark=quick for a short one; conf/benchmark/*.yaml)
    eventcap report RUNS_DIR             one table (+ CSV, plot) of the jobs of a sweep (eventcap run -m ...)
    eventcap view RUN_DIR | FILE.rrd     the run in the Rerun viewer (capture.rrd; built from the run into the view
                                         cache if missing: the run folder is only read)
    eventcap convert IN OUT              convert a recording (any format of `eventcap formats`) into the project's
                                         format, streaming (--t-start/--t-end, --roi, --calibration)
    eventcap formats                     the recording formats the registered readers take
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
from pathlib import Path

from eventcap.apps.jobs import run_job  # noqa: F401 (part of this module's API: eventcap.apps.cli.run_job)

log = logging.getLogger("eventcap")


from eventcap.apps.compose import (  # noqa: E402, F401 (config_dir is this module's API too)
    config_dir,
    stage_override_message,
    typed_override_message,
    unknown_override_message,
)


def _pipeline_for_recording(cfg, data: dict, overrides: list[str]):
    """The default command on a recording, made to fit it (:func:`eventcap.apps.compose.job_config`)."""
    from eventcap.apps.compose import job_config

    return job_config(cfg, data, overrides)


def default_cache_dir() -> str:
    return os.environ.get("EVENTCAP_CACHE_DIR", "runs/cache")


# ---------------------------------------------------------------------------------------------------------------------
# eventcap run
# ---------------------------------------------------------------------------------------------------------------------
_RUN_FAILURES: list[str] = []


def _run_job(cfg) -> bool:
    """One hydra job: compose -> validate -> run. Returns True on success."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    from eventcap.core.config import ConfigError, log_level_number

    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        logging.getLogger().setLevel(log_level_number(cfg.get("log_level", "INFO")))
    except ConfigError as exc:  # refused before anything runs, as every other setting
        log.error("%s", exc)
        _RUN_FAILURES.append(f"{run_dir}: {exc}")
        return False
    data = OmegaConf.to_container(cfg, resolve=True)
    overrides = list(HydraConfig.get().overrides.task)
    log.info("run folder: %s%s", run_dir, f" (overrides: {' '.join(overrides)})" if overrides else "")
    try:
        cfg, data = _pipeline_for_recording(cfg, data, overrides)
    except ConfigError as exc:
        log.error("%s", exc)
        _RUN_FAILURES.append(f"{run_dir}: {exc}")
        return False
    before = len(_RUN_FAILURES)
    run_job(data, run_dir, OmegaConf.to_yaml(cfg, resolve=True), _RUN_FAILURES)
    return len(_RUN_FAILURES) == before


def cmd_run(argv: list[str]) -> int:
    import hydra

    cdir = str(config_dir())
    _RUN_FAILURES.clear()
    argv = source_shorthands(argv)
    if {"--help", "-h"} & set(argv):
        return _print_run_help([a for a in argv if a not in ("--help", "-h")], cdir)

    @hydra.main(version_base="1.3", config_path=cdir, config_name="config")
    def _main(cfg) -> None:
        _run_job(cfg)

    sys.argv = ["eventcap run", *argv]
    # Hydra's own errors reach us as exceptions (not only as its printed report) so that a mistyped key is answered
    # with the project's message instead of Hydra's advice to append it with '+'.
    full_error = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        _main()
    except SystemExit as exc:  # hydra exits for --help, --cfg, and its own config errors
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        return code
    except Exception as exc:
        msg = (stage_override_message(exc, argv, cdir) or unknown_override_message(exc, argv, cdir)
               or typed_override_message(exc, argv))
        if msg is not None:
            print(f"eventcap run: {msg}", file=sys.stderr)
            return 1
        if full_error is not None:
            raise
        if type(exc).__module__.startswith(("hydra", "omegaconf")):
            print(f"eventcap run: {exc}", file=sys.stderr)  # as Hydra reports its own errors: message and cause
            if exc.__cause__ is not None:
                print(str(exc.__cause__), file=sys.stderr)
        else:  # a crash inside a job: its traceback, and the exit code Hydra gave it
            import traceback

            traceback.print_exc()
        return 1
    finally:
        if full_error is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = full_error
    return 1 if _RUN_FAILURES else 0


def _print_run_help(argv: list[str], cdir: str) -> int:
    """``eventcap run [overrides] --help``: the groups, the composed pipeline's nodes and where each node's settings
    live (eventcap/apps/runhelp.py); the composed config itself stays ``--cfg job``."""
    from eventcap.apps.runhelp import run_help

    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    try:
        print(run_help(overrides, cdir))
    except Exception as exc:  # noqa: BLE001 - an override that does not compose: said as the run would say it
        msg = stage_override_message(exc, overrides, cdir) or unknown_override_message(exc, overrides, cdir) or \
            typed_override_message(exc, overrides) or \
            f"{exc}" + (f": {exc.__cause__}" if exc.__cause__ is not None else "")
        print(f"eventcap run: {msg}", file=sys.stderr)
        return 1
    return 0


from eventcap.apps.jobs import TOP_LEVEL_KEYS  # noqa: E402

_TOP_LEVEL = {*TOP_LEVEL_KEYS, "hydra"}


def source_shorthands(argv: list[str]) -> list[str]:
    """``key=value`` for a key of a source stage (``motion=jumping_jack``, ``duration_s=1``, ``seed=0``,
    ``path=FILE``) -> ``source.key=value``, as ``eventcap run`` and ``eventcap simulate`` both take it. Top-level keys
    and config groups keep their meaning; any other argument passes unchanged (a key the chosen source does not
    have is then refused naming ``source.<key>``)."""
    import dataclasses

    from eventcap.core.registry import load_registry

    keys = {f.name for spec in load_registry().specs() if spec.kind == "source"
            for f in dataclasses.fields(spec.config)} - _TOP_LEVEL
    out = []
    for arg in argv:
        key = arg.split("=", 1)[0]
        out.append(f"source.{arg}" if "=" in arg and not arg.startswith(("-", "+", "~")) and key in keys else arg)
    return out


def cmd_simulate(argv: list[str]) -> int:
    """``eventcap simulate motion=karate_kick duration_s=1 seed=0``: a synthetic recording, written to the run folder.

    Keys of the source may be given bare, as ``eventcap run`` takes them (``motion=...`` means ``source.motion=...``:
    :func:`source_shorthands`); anything else is a normal Hydra override. The recording lands in
    ``runs/simulate/<timestamp>/source.recording.zarr``.
    """
    return cmd_run(["pipeline=simulate", "source=synthetic", "name=simulate", "export=[source.recording]",
                    "outputs.poses=null", *argv])


# ---------------------------------------------------------------------------------------------------------------------
# eventcap stages / cache
# ---------------------------------------------------------------------------------------------------------------------
def cmd_stages(args) -> int:
    from eventcap.core.registry import load_registry

    logging.getLogger("eventcap.core.registry").setLevel(logging.ERROR)  # problems are printed below, once
    reg = load_registry()
    if args.name:
        return _print_stage_config(reg, args.name)
    specs = [s for s in reg.specs() if args.kind is None or s.kind == args.kind]
    if not specs:
        print("no stages installed" + (f" of kind {args.kind!r}" if args.kind else ""))
    width = max((len(s.name) for s in specs), default=4)
    for kind in sorted({s.kind for s in specs}):
        print(f"{kind}:")
        for s in (s for s in specs if s.kind == kind):
            batch = "per batch" if s.per_batch else "whole"
            print(f"  {s.name:<{width}}  v{s.version:<3} {batch:<9}  {s.description}")
            if args.verbose:
                print(f"  {'':<{width}}  from {s.origin}")
    for p in reg.problems:
        print(f"warning: {p}", file=sys.stderr)
    return 0


def _print_stage_config(reg, name: str) -> int:
    """Every key of a stage's config with its default, choices and meaning, group by group: the one place they are
    stated. ``name``: a stage, a node of a pipeline (the default pipeline's first), or a variant (stages/<node>=name)."""
    import textwrap

    from eventcap.core.registry import UnknownStageError

    node, how = _resolve_stage_name(name)
    try:
        spec = reg.get(node[1] if node else name)
    except UnknownStageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if how:
        print(how)
    print(f"{spec.name} (v{spec.version}, {spec.kind}, {'per batch' if spec.per_batch else 'whole recording'}): "
          f"{spec.description}")
    prefix = f"stages.{node[0]}" if node else "stages.<node>"
    print(f"  from {spec.origin}; set a key with {prefix}.<key>=value" + ("" if node else " (the node that runs this "
                                                                          "stage: `eventcap run --help` names it)"))
    try:
        default = spec.config()
    except TypeError:
        default = None
    _print_settings(spec.config, default, "", textwrap)
    return 0


def _print_settings(config_class, default, prefix: str, textwrap) -> None:
    """The settings of a config class (groups opened, each with its help) with their defaults."""
    import dataclasses

    from eventcap.params import allowed_values, is_group

    plain = [f for f in dataclasses.fields(config_class) if not is_group(f)]
    groups = [f for f in dataclasses.fields(config_class) if is_group(f)]
    for f in plain:
        if default is not None:
            value = getattr(default, f.name)
        elif f.default is not dataclasses.MISSING:
            value = f.default
        elif f.default_factory is not dataclasses.MISSING:
            value = f.default_factory()
        else:
            value = "(required)"
        meta = f.metadata
        allowed = allowed_values(f)  # a number's declared range, in words
        extra = (f"; one of {' | '.join(map(str, meta['choices']))}" if meta.get("choices") else "") + \
            (f"; {allowed}" if allowed and not meta.get("choices") else "") + \
            ("" if meta.get("affects_result", True) else "; not part of the cache key")
        print(f"  {prefix}{f.name} = {value!r}{extra}")
        for line in textwrap.wrap(meta.get("help", ""), 110):
            print(f"      {line}")
    for f in groups:
        print(f"  {prefix}{f.name}: {f.metadata.get('help', '')}")
        _print_settings(f.metadata["group"], None if default is None else getattr(default, f.name),
                        f"{prefix}{f.name}.", textwrap)


def _resolve_stage_name(name: str) -> tuple[tuple[str, str] | None, str]:
    """((node, stage), what was resolved) when ``name`` is a node of a pipeline (the default pipeline's first) or a
    variant of a node (conf/stages/<node>/<name>.yaml); (None, "") for anything else (a stage's name)."""
    import yaml

    cdir = config_dir()
    default_nodes = _default_pipeline_nodes(cdir)
    if name in default_nodes:
        return (name, default_nodes[name]), (f"node {name!r} of the default pipeline runs stage "
                                             f"{default_nodes[name]!r}; its settings are stages.{name} (another "
                                             f"stage: stages/{name}=<variant>: "
                                             f"{' | '.join(_variants(cdir, name))})")
    runs = [n for n, st in default_nodes.items() if st == name]
    if runs:
        return (runs[0], name), f"stage {name!r} runs at node {runs[0]!r} of the default pipeline"
    found = [(f.parent.name, f, _variant_stage(f)) for f in sorted((cdir / "stages").glob(f"*/{name}.yaml"))]
    found = sorted((x for x in found if x[2] and x[2] != name), key=lambda x: (x[0] not in default_nodes, x[0]))
    if found:
        node, f, stage = found[0]
        also = "".join(f"; also of node {n!r} (stages/{n}={name}, stage {st!r})" for n, _, st in found[1:])
        return (node, stage), (f"{name!r} is a variant of node {node!r} (stages/{node}={name}: "
                               f"{f.relative_to(cdir.parent)}) running stage {stage!r}{also}")
    for p in sorted((cdir / "pipeline").glob("*.yaml")):
        d = yaml.safe_load(p.read_text()) or {}
        if name not in ((d.get("pipeline", d) or {}).get("nodes") or {}):
            continue
        for entry in d.get("defaults") or []:
            if isinstance(entry, dict):
                (k, v), = entry.items()
                if k.lstrip("/").split("@")[0] == f"stages/{name}":
                    stage = _variant_stage(cdir / "stages" / name / f"{v}.yaml")
                    if stage:
                        return (name, stage), (f"node {name!r} of pipeline={p.stem} (not the default pipeline) runs "
                                               f"stage {stage!r} (stages/{name}={v}); its settings are stages.{name}")
    return None, ""


def _default_pipeline_nodes(cdir: Path) -> dict[str, str]:
    """The default pipeline's stage nodes and the stage each runs by default."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(cdir), version_base="1.3"):
            cfg = compose(config_name="config")
    except Exception:  # noqa: BLE001 - best effort
        return {}
    stages = cfg.get("stages") or {}
    return {str(n): str(stages[n].stage) for n in cfg.pipeline.nodes if n in stages}


def _variants(cdir: Path, node: str) -> list[str]:
    return sorted(p.stem for p in (cdir / "stages" / node).glob("*.yaml"))


def _variant_stage(path: Path) -> str | None:
    """The stage a variant file runs (its ``stage:``, or that of the variant it starts from)."""
    import yaml

    d = yaml.safe_load(path.read_text()) or {}
    if "stage" in d:
        return str(d["stage"])
    for entry in d.get("defaults") or []:
        if isinstance(entry, str) and entry.startswith("/stages/"):
            ref = entry.split("@")[0].lstrip("/")
            return _variant_stage(path.parents[2] / f"{ref}.yaml")
        if isinstance(entry, str) and entry.startswith("/stage/"):
            return entry.split("@")[0].split("/")[-1]
        if isinstance(entry, str) and entry not in ("_self_",):
            return _variant_stage(path.parent / f"{entry}.yaml")
    return None


def cmd_formats() -> int:
    """The registered readers (eventcap/io/registry.py): one block per format."""
    from eventcap.io.registry import readers

    for spec in readers().specs():
        wraps = ", ".join(f"2^{w.bit_length() - 1} µs" for w in spec.wraps_us)
        print(f"{spec.name:<8} {spec.description}")
        details = [("files", ", ".join(spec.extensions) + (" or a folder" if spec.folder else "")),
                   ("signature", " or ".join(repr(m) for m in spec.magic)), ("also reads", spec.extras),
                   ("time counter", wraps), ("columns=, time_unit=", "yes" if spec.columns else ""),
                   ("sensor size", "" if spec.declares_size else "inferred from the events unless given"),
                   ("decoded by", spec.library), ("from", spec.origin)]
        for label, value in details:
            if value:
                print(f"{'':<9}{label}: {value}")
    print("eventcap (source.format=eventcap): the project's own zarr recording (eventcap convert writes it)")
    return 0


def cmd_cache(args) -> int:
    from eventcap.core.cache import Cache, CacheError
    from eventcap.core.ownership import FAILURE_FILE

    try:
        cache = Cache(args.cache_dir, create=False)  # a missing directory is said so, not created
        if args.action == "ls":
            entries = cache.entries()
            total = 0
            print(f"{'stage':<16} {'key':<14} {'node':<14} {'batch':>5} {'size':>10}  created")
            for e in entries:
                m = e.manifest
                b = (m.get("batch") or {}).get("index")
                size = e.size_bytes()
                total += size
                print(f"{e.stage:<16} {e.key[:12]:<14} {str(m.get('node', '')):<14} {'' if b is None else b:>5} "
                      f"{_human(size):>10}  {m.get('created', '')}")
            nfail = len(list((cache.root / "failures").glob("*.json")))
            print(f"{len(entries)} entries, {_human(total)} in {cache.root}; {nfail} recorded failures")
        elif args.action == "explain":
            _explain(cache, args.key)
        elif args.action == "gc":
            cache.ensure_marked()  # deletes only inside a cache the tool made (eventcap/core/ownership.py)
            removed = cache.clean_orphans(max_age_s=0 if args.all else 24 * 3600)
            n = 0
            import shutil
            import time

            cutoff = time.time() - args.older_than * 86400 if args.older_than is not None else None
            for e in cache.entries():
                if args.all or (cutoff is not None and (e.path / "manifest.json").stat().st_mtime < cutoff):
                    shutil.rmtree(e.path, ignore_errors=True)
                    n += 1
            for f in (cache.root / "failures").glob(".*.tmp"):
                if FAILURE_FILE.match(f.name) and not f.is_symlink():
                    f.unlink(missing_ok=True)
            print(f"removed {len(removed)} orphaned temporary entries and {n} cache entries from {cache.root}")
    except CacheError as exc:
        print(f"eventcap cache: {exc}", file=sys.stderr)
        return 2
    return 0


def _read_for_preview(args):
    """The recording at ``args.recording`` in any format the readers take (the project's zarr format too), and a
    line saying what was read."""
    from eventcap.io.convert import is_project_recording, recording_from_raw

    from eventcap.io.source import check_regular

    path = Path(args.recording)
    check_regular(path)  # a pipe, a device, a link loop: refused at once, never opened
    if args.format in ("", None, "eventcap") and is_project_recording(path):
        from eventcap.io.convert import read_project_recording

        return read_project_recording(path), "eventcap (zarr)"
    from eventcap.io import read_recording

    raw = read_recording(path, format=args.format or None, width=args.width or None, height=args.height or None,
                         time_unit=args.time_unit or None, columns=args.columns or None,
                         max_gap_s=getattr(args, "max_gap_s", None))
    rec = recording_from_raw(raw, calibration=args.calibration or None, hint="give --calibration")
    return rec, raw.format


def preview_path(recording, out=None) -> Path:
    """Where ``eventcap preview`` writes its PNG: ``out`` (a folder: the name inside it), else the current folder;
    never beside the recording (a data folder, or a checkout's tests/data/, is no place for it)."""
    name = f"{Path(recording).name.split('.')[0] or 'recording'}.preview.png"
    if out is None or str(out) == "":
        return Path(name)
    return Path(out) / name if Path(out).is_dir() else Path(out)


def cmd_preview(args) -> int:
    """A PNG of a recording in any readable format: frame (or image from events), true sharp image, events,
    ground-truth skeleton; by default at the recording's most active moment. Says what it read."""
    import cv2
    import numpy as np
    import zarr

    from eventcap.artifacts import ArtifactError
    from eventcap.imaging.viz import describe_recording, most_active_time, recording_overview
    from eventcap.io.checks import timing_note

    try:
        rec, fmt = _read_for_preview(args)
        print(f"read {args.recording}: {fmt}; {describe_recording(rec)}")
        grid = timing_note(rec.events.events["t"])
        if grid:
            print(f"note: {grid}")
        latent = None
        if args.latent:
            from eventcap.artifacts.tracking import LatentFrames

            latent = LatentFrames.from_zarr(zarr.open_group(str(args.latent), mode="r"), where=str(args.latent))
        if args.tracks:
            from eventcap.artifacts import BatchPlan
            from eventcap.artifacts.tracking import SlicedTracks
            from eventcap.imaging.viz import tracks_overview

            if latent is None:
                raise ArtifactError("--tracks needs --latent (the sharpened frames to draw on)")
            sliced = SlicedTracks.from_zarr(zarr.open_group(str(args.tracks), mode="r"), where=str(args.tracks))
            plan = BatchPlan.between_frames(rec.frames.t_us)
            batch = plan.batch(int(np.searchsorted(plan.t0_us, sliced.t_us[0])))
            img, what = tracks_overview(rec, latent, sliced, batch), f"batch {batch.index}"
        else:
            t_us, what = None, f"frame {args.frame}"
            if args.t is not None:
                t_us, what = int(round(args.t * 1e6)), f"t = {args.t:.3f} s (--t)"
            elif args.frame is None:
                t_us, count = most_active_time(rec.events.events, 20_000)
                what = f"t = {t_us / 1e6:.3f} s, the most active moment ({count:,} events in 20 ms; --t or --frame " \
                       f"to choose)"
            img = recording_overview(rec, frame_index=args.frame, scale=args.scale, latent=latent,
                                     reconstruct=True if args.reconstruct else None, rate_hz=args.rate, t_us=t_us)
    except (ArtifactError, OSError, ValueError) as exc:  # RecordingError is a ValueError
        print(f"eventcap preview: {exc}", file=sys.stderr)
        return 2
    out = preview_path(args.recording, args.out)
    cv2.imwrite(str(out), img)
    print(f"showing {what}; wrote {out} ({img.shape[1]}x{img.shape[0]})")
    return 0


def cmd_view(args) -> int:
    """Show a run in the Rerun viewer: its ``capture.rrd``, else one built from the run folder into the view cache
    (the run folder is only read). The viewer runs in the foreground and ends with this command, however it is
    stopped (:func:`eventcap.apps.viewer.run_viewer`)."""
    from eventcap.apps.outputs import build_run_recording
    from eventcap.core.runrecord import RunRecordError
    from eventcap.apps.viewer import RRD_NAME, ViewError, has_display, how_to_view, require_rerun, rerun_command, \
        run_viewer, view_cache_dir, web_viewer_command, web_viewer_url

    try:
        require_rerun()
    except ImportError as exc:
        print(f"eventcap view: {exc}", file=sys.stderr)
        return 2
    target = Path(args.target)
    again = args.rebuild or args.recompute
    try:
        if target.is_file() and target.suffix == ".rrd":
            rrd = target
        elif target.is_dir():
            rrd, built = target / RRD_NAME, view_cache_dir(target) / RRD_NAME
            if again or not rrd.is_file():
                rrd = built
            if again or not rrd.is_file():
                print(f"eventcap view: building {rrd} from the run (its config.yaml, run.json and the cache; the run "
                      f"folder is only read)", file=sys.stderr)
                rrd = build_run_recording(target, recompute=args.recompute, out_dir=built.parent)
        else:
            raise ViewError(f"{target}: expected a run folder (runs/<name>/<timestamp>/) or an .rrd file")
    except (ViewError, RunRecordError) as exc:
        print(f"eventcap view: {exc}", file=sys.stderr)
        return 2
    if args.web:
        print(f"eventcap view: serving the web viewer of {rrd}: open {web_viewer_url(args.port, args.grpc_port)} "
              f"(Ctrl-C stops it)", flush=True)
        return run_viewer([*rerun_command(), *web_viewer_command(rrd, args.port, args.grpc_port)])
    if has_display() and not args.no_open:
        print(f"eventcap view: showing {rrd} in the Rerun viewer (closing it or Ctrl-C ends both)", flush=True)
        return run_viewer([*rerun_command(), str(rrd)])
    why = "" if args.no_open else "no display here; "
    print(f"eventcap view: {rrd} ({rrd.stat().st_size / 1e6:.1f} MB): {why}"
          f"{how_to_view(rrd, args.port, args.grpc_port, target)}")
    return 0


def cmd_convert(args) -> int:
    """Convert a recording into the project's format, printing progress (stderr) and a summary (stdout)."""
    from eventcap.io import RecordingError
    from eventcap.io.convert import convert_recording, roi_from_corners, window_from_seconds

    tty = sys.stderr.isatty()
    shown = {"at": 0.0, "any": False}

    def progress(written: int, read: int, seconds: float) -> None:
        if seconds - shown["at"] < 1.0:
            return
        shown["at"], shown["any"] = seconds, True
        line = f"eventcap convert: {read:,} events read, {written:,} written, {read / seconds / 1e6:.2f} M events/s"
        # On a terminal the line is redrawn in place; in a log, one line per update.
        print("\r" + line if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)

    try:
        if (args.width is None) != (args.height is None):
            raise ValueError(f"give both --width and --height or neither, got width={args.width}, "
                             f"height={args.height}")
        window = window_from_seconds(args.t_start, args.t_end)
        roi = roi_from_corners(args.roi) if args.roi else None
        stats = convert_recording(args.input, args.output, format=args.format, chunk_events=args.chunk_events,
                                  calibration=args.calibration, width=args.width, height=args.height,
                                  time_window_us=window, roi=roi, time_unit=args.time_unit,
                                  overwrite=args.overwrite, progress=progress, columns=args.columns or None,
                                  y_up=args.y_up, max_gap_s=args.max_gap_s)
    except (RecordingError, ValueError, OSError) as exc:
        if shown["any"] and tty:
            print(file=sys.stderr)
        print(f"eventcap convert: {exc}", file=sys.stderr)
        return 2
    if shown["any"] and tty:
        print(file=sys.stderr)
    s = stats
    span_s = (s["t_last_us"] - s["t_first_us"]) / 1e6
    print(f"wrote {s['out']}: {s['events']:,} events ({span_s:.3f} s), {s['frames']} frames, "
          f"{s['width']}x{s['height']} (width x height), from {s['format']}; {s['camera']}")
    print(f"read {s['events_read']:,} events in {s['seconds']:.1f} s ({s['events_per_s'] / 1e6:.2f} M events/s), "
          f"{_human(s['bytes'])} on disk; {len(s['repairs'])} repair(s)"
          + "".join("\n  repaired: " + r for r in s["repairs"]))
    return 0


_BENCHMARK_HELP = """Run every method of conf/benchmark/<preset>.yaml on every synthetic sequence (motion x seed) through the
pipeline, all runs sharing one cache (a second call recomputes nothing), and print Table 1 (AE.all / AE.raw /
AE.nonRaw mean ± STD, data rate), AE per motion and time per batch per stage; writes table.csv, runs.csv,
benchmark.json and fig7_per_frame_error.png into <out>.

  eventcap benchmark                         the full suite (6 motions x 2 seeds, conf/benchmark/default.yaml)
  eventcap benchmark benchmark=quick         2 motions x 1 seed x 0.2 s
  eventcap benchmark benchmark=open          captures drawn from their seeds (tuning seeds 0-19), per group
  eventcap benchmark benchmark=open_check    the same on the check seeds 100-119: for reporting only
  eventcap benchmark motions=[karate_kick] seeds=[0,1,2] duration_s=1
  eventcap benchmark stages.track.stitch_px=2  an override of every run (not a benchmark key)
"""


def cmd_benchmark(argv: list[str]) -> int:
    from eventcap.apps.benchmark import main as benchmark_main

    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    try:
        return benchmark_main(argv, config_dir())
    except ValueError as exc:
        print(f"eventcap benchmark: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # hydra's composition errors name the bad override
        if type(exc).__module__.startswith(("hydra", "omegaconf")):
            print(f"eventcap benchmark: {exc}", file=sys.stderr)
            return 2
        raise


def _explain(cache, prefix: str) -> None:
    e = cache.find(prefix)
    m = e.manifest
    doc = m["doc"]
    print(f"key      {e.key}")
    print(f"stage    {doc['stage']} v{doc['version']}   node {m.get('node')}   created {m.get('created')}")
    if m.get("batch"):
        b = m["batch"]
        print(f"batch    {b['index']}  [{b['t0_us']} us, {b['t1_us']} us)")
    outs = ", ".join(f"{p}: {o['type']} v{o['schema_version']}" for p, o in m["outputs"].items())
    print(f"outputs  {outs}")
    print(f"size     {_human(e.size_bytes())} in {len(m['files'])} files; computed in {m.get('elapsed_s', '?')} s")
    print("config (fields that affect the result):")
    for k, v in sorted(doc["config"].items()):
        print(f"  {k} = {json.dumps(v)}")
    for k, v in sorted(doc.get("files", {}).items()):
        print(f"  file {k}: sha256 {v[:16]}…")
    print("inputs:")
    for port, key in sorted(doc.get("inputs", {}).items()):
        keys = key if isinstance(key, str) else key.get("node_key", "")
        try:
            up = cache.find(keys[:40])
            desc = f"{up.stage} (node {up.manifest.get('node')})"
        except Exception:
            desc = "per-batch node or not in cache"
        print(f"  {port} <- {keys[:12]}  {desc}")


def _human(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def _pin_threads() -> None:
    """One BLAS/OpenMP thread per process unless the user says otherwise: the heavy work is parallel over batches
    (processes), and BLAS threads fighting over a few cores make small per-frame products many times slower."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


#: Top-level run settings also taken in the ``--option value`` style by the Hydra subcommands (run, simulate,
#: benchmark), as the other subcommands take ``key=value``.
_RUN_OPTIONS = {"--cache-dir": "cache_dir", "--log-level": "log_level", "--batches": "batches"}


def run_options_as_overrides(argv: list[str]) -> list[str]:
    """``--cache-dir X`` / ``--cache-dir=X`` -> ``cache_dir=X`` (and the other :data:`_RUN_OPTIONS`), for Hydra."""
    out, i = [], 0
    while i < len(argv):
        flag, eq, value = argv[i].partition("=")
        if flag in _RUN_OPTIONS:
            if not eq:
                if i + 1 >= len(argv):
                    raise SystemExit(f"eventcap: {flag} needs a value")
                i, value = i + 1, argv[i + 1]
            out.append(f"{_RUN_OPTIONS[flag]}={value}")
        else:
            out.append(argv[i])
        i += 1
    return out


def settings_as_options(subparsers, argv: list[str]) -> list[str]:
    """``key=value`` -> ``--key value`` for the options of the chosen argparse subcommand (``cache_dir=X`` as
    ``--cache-dir X``, ``all=true`` as ``--all``), so every subcommand takes both styles. A ``word=...`` that names
    no option of the subcommand is refused with the ones it has; other arguments (paths) pass unchanged."""
    import difflib

    if not argv or argv[0] not in subparsers.choices:
        return argv
    sub = subparsers.choices[argv[0]]
    options = {}
    for action in sub._actions:
        for opt in action.option_strings:
            if opt.startswith("--") and opt != "--help":
                options[opt[2:].replace("-", "_")] = (opt, action)
    out = [argv[0]]
    for arg in argv[1:]:
        m = re.fullmatch(r"([A-Za-z][A-Za-z0-9_-]*)=(.*)", arg, flags=re.S)
        if m is None or arg.startswith("-"):
            out.append(arg)
            continue
        key, value = m.group(1).replace("-", "_"), m.group(2)
        if key not in options:
            close = difflib.get_close_matches(key, list(options), n=1, cutoff=0.6)
            if close or not Path(arg).exists():
                known = ", ".join(sorted(options)) or "none"
                hint = f"; did you mean {close[0]}=...?" if close else ""
                raise SystemExit(f"eventcap {argv[0]}: unknown setting {key!r} (settings: {known}){hint}")
            out.append(arg)
            continue
        opt, action = options[key]
        if action.nargs == 0:  # a flag: true / false
            if value.lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise SystemExit(f"eventcap {argv[0]}: {key}: expected true or false, got {value!r}")
            if value.lower() in ("true", "1", "yes"):
                out.append(opt)
        else:
            out += [opt, *(value.split(",") if action.nargs not in (None, "?") else [value])]
    return out


def _add_preview_parser(sub) -> None:
    p = sub.add_parser("preview", help="PNG of a recording: frame (or image from events), sharp image, events, "
                                       "ground-truth skeleton")
    p.add_argument("recording", help="a recording in any format a reader takes (`eventcap formats` lists them) or "
                                      "the project's zarr (e.g. runs/simulate/*/source.recording.zarr)")
    p.add_argument("--frame", type=int, default=None, help="intensity frame (or event-only image) index; default: "
                                                            "the recording's most active moment")
    p.add_argument("--t", type=float, default=None, help="time to show, seconds from the first event (the nearest "
                                                         "frame)")
    p.add_argument("--format", default="", help="force a format (a name of `eventcap formats`, as source.format); "
                                                "default: detect it")
    p.add_argument("--width", type=int, default=0, help="sensor width for files that do not store it")
    p.add_argument("--height", type=int, default=0, help="sensor height for files that do not store it")
    p.add_argument("--columns", default="", help="column order of unnamed array/text columns, e.g. x,y,t,p")
    p.add_argument("--time-unit", default="", help="unit of array/text time columns: s | ms | us | ns")
    p.add_argument("--max-gap-s", type=float, default=None, metavar="S",
                   help="longest pause between neighbouring events taken as real (default 60 s); longer jumps in "
                        "time are refused or repaired")
    p.add_argument("--calibration", default="", help="rpg calib.txt (fx fy cx cy [k1 k2 p1 p2 k3])")
    p.add_argument("--scale", type=int, default=2, help="upscaling of the panels")
    p.add_argument("--out", help="output PNG, or a folder for it (default: <name>.preview.png in the current "
                                 "folder)")
    p.add_argument("--latent", help="sharpened frames (e.g. runs/.../sharpen.latent.zarr) to show beside the frame")
    p.add_argument("--tracks", help="one batch's sliced tracks (e.g. runs/.../slice.sliced/batch0003.zarr) to draw")
    p.add_argument("--reconstruct", action="store_true", help="add the image reconstructed from the events alone "
                                                               "(always shown for event-only recordings)")
    p.add_argument("--rate", type=float, default=25.0, help="event-only recordings: image times every 1/rate s")


def _parser() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    """The command line of the subcommands argparse handles (run, simulate and benchmark take Hydra overrides), and
    its subparsers."""
    parser = argparse.ArgumentParser(prog="eventcap", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("run", help="run the pipeline (hydra overrides follow; see `eventcap run --help`)")
    sub.add_parser("simulate", help="write a synthetic recording (e.g. motion=karate_kick duration_s=1 seed=0)")
    sub.add_parser("benchmark", usage="eventcap benchmark [benchmark=PRESET] [KEY=VALUE ...] [RUN_OVERRIDE ...]",
                   help="Table 1 / Fig. 7 on synthetic captures (overrides follow: benchmark=quick, "
                                     "motions=[a,b], seeds=[0], duration_s=1, or any run override)",
                   description=_BENCHMARK_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p = sub.add_parser("report", help="one table (+ report.csv, report.png) of the jobs of a sweep folder")
    p.add_argument("runs_dir", metavar="RUNS_DIR", help="a sweep folder (runs/<name>/multirun_<ts>/) or any folder "
                                                        "holding run folders")
    p.add_argument("--out", help="where report.csv / report.png go (default: RUNS_DIR)")
    p.add_argument("--metrics", help="node.port of the metrics to show (default: evaluate.metrics)")
    p.add_argument("--column", action="append", default=[], metavar="KEY",
                   help="one more column: a dotted key into the metrics (e.g. per_joint_mm.l_wrist); repeatable")
    p.add_argument("--no-plot", action="store_true", help="no report.png")
    p = sub.add_parser("stages", help="list installed stages, or one stage's config keys with their defaults")
    p.add_argument("name", nargs="?", help="a stage: print its config keys, defaults and meaning")
    p.add_argument("--kind", help="only stages of this kind (e.g. track)")
    p.add_argument("-v", "--verbose", action="store_true", help="show where each stage comes from")
    sub.add_parser("formats", help="the recording formats the registered readers take: name, file names, signature, "
                                   "what is read, time counters (eventcap/io/registry.py)")
    p = sub.add_parser("cache", help="inspect or clean the stage cache")
    p.add_argument("action", choices=["ls", "explain", "gc"])
    p.add_argument("key", nargs="?", help="key (or unique prefix) for explain")
    p.add_argument("--cache-dir", default=default_cache_dir(), help="cache root (default: %(default)s)")
    p.add_argument("--older-than", type=float, default=None, help="gc: also remove entries older than this many days")
    p.add_argument("--all", action="store_true", help="gc: remove every entry")
    _add_preview_parser(sub)
    p = sub.add_parser("view", help="the run in the Rerun viewer (capture.rrd; built from the run folder if missing)")
    p.add_argument("target", metavar="RUN_DIR", help="a run folder (runs/<name>/<timestamp>/) or an .rrd file")
    p.add_argument("--rebuild", action="store_true", help="build the recording again (into the view cache: "
                                                           "$EVENTCAP_VIEW_DIR or ~/.cache/eventcap/views) even if "
                                                           "the run folder or the cache has one")
    p.add_argument("--recompute", action="store_true", help="run the run's config again first (cache hits; "
                                                             "recomputes entries gone from the cache)")
    p.add_argument("--web", action="store_true", help="serve the web viewer on 127.0.0.1 (for a browser)")
    p.add_argument("--port", type=int, default=9090, help="web viewer port, HTTP (default: %(default)s)")
    p.add_argument("--grpc-port", type=int, default=9876, help="web viewer's data port (default: %(default)s)")
    p.add_argument("--no-open", action="store_true", help="only build the recording and print how to open it")
    p = sub.add_parser("convert", help="convert a recording into the project's format (streaming, bounded memory)")
    p.add_argument("input", metavar="IN", help="the recording, in any format a reader takes (`eventcap formats` "
                                                "lists them)")
    p.add_argument("output", metavar="OUT", help="the folder to write (a zarr group, e.g. rec.zarr)")
    p.add_argument("--format", help="force the input format (a name of `eventcap formats`)")
    p.add_argument("--calibration", help="rpg calib.txt (fx fy cx cy [k1 k2 p1 p2 k3]) of the full sensor, "
                                         "overriding the file's")
    p.add_argument("--width", type=int, help="sensor width for files that do not store it")
    p.add_argument("--height", type=int, help="sensor height for files that do not store it")
    p.add_argument("--t-start", type=float, default=0.0, metavar="S", help="start, seconds from the first event")
    p.add_argument("--t-end", type=float, default=0.0, metavar="S", help="end, seconds from the first event "
                                                                        "(0 = to the end)")
    p.add_argument("--roi", type=int, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                   help="keep the region x0 <= x < x1, y0 <= y < y1 (moved to 0, 0)")
    p.add_argument("--time-unit", help="unit of array/text time columns when the default is wrong (s, ms, us, ns)")
    p.add_argument("--columns", help="column order of unnamed array/text columns, e.g. x,y,t,p")
    p.add_argument("--y-up", action="store_true", help="the file's y axis points up (origin bottom-left)")
    p.add_argument("--max-gap-s", type=float, default=None, metavar="S",
                   help="longest pause between neighbouring events taken as real (default 60 s); longer jumps in "
                        "time are refused or repaired")
    p.add_argument("--chunk-events", type=int, default=1 << 20, metavar="N",
                   help="events decoded per chunk (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    return parser, sub


class _PipeSafeStdout:
    """sys.stdout that a closed reader (``eventcap stages | head``) silences instead of breaking: the first write
    after the reader went away points the file descriptor at /dev/null, and the command goes on quietly (its log
    file still gets everything). Anything else is the wrapped stream's."""

    def __init__(self, stream):
        self._stream = stream

    def _gone(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())
        os.close(devnull)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._gone()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._gone()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    """The ``eventcap`` command; returns its exit code. Output piped into a reader that stops early (``| head``)
    ends quietly (:class:`_PipeSafeStdout`), whichever the subcommand."""
    stdout = sys.stdout
    try:
        stdout.fileno()
        sys.stdout = _PipeSafeStdout(stdout)
    except (AttributeError, OSError, ValueError):  # not a file (e.g. pytest's capture): nothing to protect
        pass
    try:
        return _main(argv)
    finally:
        sys.stdout.flush()
        sys.stdout = stdout


def _main(argv: list[str] | None = None) -> int:
    _pin_threads()  # before anything imports numpy
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("run", "simulate", "benchmark"):
        argv = [argv[0], *run_options_as_overrides(argv[1:])]
    if argv and argv[0] == "run":
        return cmd_run(argv[1:])
    if argv and argv[0] == "simulate":
        return cmd_simulate(argv[1:])
    if argv and argv[0] == "benchmark" and not ({"-h", "--help"} & set(argv[1:])):
        return cmd_benchmark(argv[1:])
    parser, sub = _parser()
    args = parser.parse_args(settings_as_options(sub, argv))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.command == "stages":
        return cmd_stages(args)
    if args.command == "report":
        from eventcap.apps.report import ReportError, report

        try:
            report(Path(args.runs_dir), args.out, args.metrics, args.column, plot=not args.no_plot)
        except ReportError as exc:
            print(f"eventcap report: {exc}", file=sys.stderr)
            return 2
        return 0
    if args.command == "formats":
        return cmd_formats()
    if args.command == "preview":
        return cmd_preview(args)
    if args.command == "convert":
        return cmd_convert(args)
    if args.command == "view":
        return cmd_view(args)
    if args.command == "cache":
        if args.action == "explain" and not args.key:
            parser.error("cache explain needs a KEY")
        return cmd_cache(args)
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
