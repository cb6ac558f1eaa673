"""The `splittag` console script: one entry point, one subcommand per capability."""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from shared.model.precision import PRECISION_CHOICES, PRECISIONS, ModelFileError
from shared.model.views import VIEW_COUNTS
from shared.runtime.logs import setup_logging
from shared.tools import settings_doc
from shared.tools.options import add_model_options, model_from_args
from shared.tools.topology import EDGE_PORT, Topology
from shared.training.settings import QuantizeSettings, TrainSettings
from shared.wire.cuts import N_CUTS

if TYPE_CHECKING:
    from shared.transport.session import ZenohSettings

VIEWS_HELP = (
    "test-time views: the network on each ROI and 1, 3 or 7 of its flips and turns, keypoints averaged "
    "(that many times the network time; shared/model/views.py)"
)


def _cmd_demo(args: argparse.Namespace) -> int:
    import json

    from shared.tools.launch import run_pipeline

    summary = run_pipeline(
        args.config,
        duration_secs=args.duration,
        controller=args.controller,
        link=args.link,
        extra=_launch_extra(args),
    )
    print(json.dumps({k: v for k, v in summary.items() if k != "exit_codes"}, indent=2))
    return 0 if summary.get("frames") else 1


def _cmd_up(args: argparse.Namespace) -> int:
    import json

    from shared.tools.launch import run_pipeline

    summary = run_pipeline(
        args.config,
        duration_secs=args.duration,
        runs_root=args.runs,
        controller=args.controller,
        link=args.link,
        extra=_launch_extra(args),
        only=args.only,
    )
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_fleet(args: argparse.Namespace) -> int:
    import json

    from shared.tools.fleet import FleetPlan, make_certs, run_fleet

    if args.make_certs:
        plan = FleetPlan.from_config(args.config)
        if plan.certs is None:
            print(f"splittag fleet: {args.config} sets no [fleet] certs folder", file=sys.stderr)
            return 2
        names = make_certs(plan)
        print(f"certificates for {' '.join(names)} in {plan.certs}/ (CA {plan.certs}/ca.pem)")
        return 0
    summary = run_fleet(args.config, duration_secs=args.duration, runs_root=args.runs, only=args.only)
    print(json.dumps({k: v for k, v in summary.items() if k != "exit_codes"}, indent=2))
    return 0


def _cmd_down(args: argparse.Namespace) -> int:
    import contextlib
    import os
    import signal
    import time

    run = args.runs / "current"
    pids = run / "pids"
    if not pids.is_file():
        print(f"no running deployment ({pids} not found)")
        return 1
    pid, services = _live_run_processes(run)
    if pid is None and not services:
        print(f"no running deployment in {run.resolve()} (its processes have ended)")
        _finish_orphaned(run, [])
        return 1
    if pid is not None:
        # The launcher supervises (it would restart a service stopped behind its back): stop it, and
        # it stops the services in order.
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGINT)
    else:
        for _, service_pid in services:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(service_pid, signal.SIGINT)
    for name, service_pid in services:
        print(f"stopping {name} ({service_pid})")
    waiting = [*([pid] if pid else []), *(p for _, p in services)]
    start = time.monotonic()
    dumped = False
    while any(_running(p) for p in waiting) and time.monotonic() < start + 90:
        if not dumped and time.monotonic() > start + 30:  # a hung service says where it hangs, in its log
            dumped = True
            for name, service_pid in services:
                if _running(service_pid):
                    print(f"{name} ({service_pid}) has not stopped after 30 s: its thread stacks go to its log")
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(service_pid, signal.SIGUSR1)
        time.sleep(0.2)
    if pid is None:  # the launcher had died: finish the run as it would have
        alive = [name for name, p in services if _running(p)]
        _finish_orphaned(run, [name for name, _ in services], alive)
    return 0


def _finish_orphaned(run: Path, stopped: list[str], still_running: list[str] | None = None) -> None:
    """A run whose launcher died: its summary, merged recording and no stale pid files."""
    from shared.tools.launch import finish_orphaned_run

    summary = finish_orphaned_run(run.resolve(), stopped, still_running=still_running or [])
    print(f"the run's launcher had died: wrote {run.resolve() / 'summary.json'}", flush=True)
    if "recording" in summary:
        print(f"merged the recording into {summary['recording']}", flush=True)
    if still_running:
        print(f"still running after 90 s: {', '.join(still_running)} (their recording parts are left as they are)")


def _cmdline(pid: int) -> str:
    """A process's command line (empty when it is gone or unreadable)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _running(pid: int) -> bool:
    """True while the process exists and is not a zombie waiting for its parent."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z"


def split_endpoint(connect: list[str] | None, *, tls: bool) -> list[str]:
    """Where a reader connects: the endpoints given (`--connect` again for a second one, tried when the
    first is away, as slam and the launcher's monitor have the robot's router), else the local edge
    router (tls/ when certificates are given: `--certs` alone used to try plain TCP)."""
    if connect:
        return list(connect)
    default = Topology().edge_router
    return ["tls/" + default.split("/", 1)[1] if tls else default]


def _reader_settings(
    args: argparse.Namespace, command: str, runs: Path = Path("runs"), *, steers: bool = False
) -> ZenohSettings | None:
    """The client session of a command that reads or steers a running deployment (split, watch, map,
    stats): the endpoint, TLS identity and robot id checked; None after saying what is wrong. Without
    --connect, a note when the live deployment in runs/current listens elsewhere: the default endpoint
    may be another deployment's (a trial's watch of its own run on other ports silently recorded the
    poses of a second deployment on the default ones). A command that `steers` (split set or release,
    map --save) is refused instead: it would change whoever owns the default endpoint (an integrator's
    note: `split set 3` on a shared host)."""
    from shared.transport.session import TlsSettings, ZenohSettings

    tls = TlsSettings.from_dir(args.certs, args.identity) if args.certs else None
    connect = split_endpoint(args.connect, tls=tls is not None)
    if not args.connect and "listens at" in (hint := _endpoint_hint(args, runs)):
        if steers:
            print(
                f"splittag {command}: not sent to the default {connect[0]}{hint}: give --connect, that one or "
                f"--connect {connect[0]} for the deployment there",
                file=sys.stderr,
            )
            return None
        print(f"splittag {command}: note: reading the default {connect[0]}{hint}", file=sys.stderr)
    if tls is None and (secure := [c for c in connect if c.startswith("tls/")]):
        print(f"splittag {command}: {secure[0]} is a TLS endpoint: give --certs (and --identity)", file=sys.stderr)
        return None
    if tls is not None and (plain := [c for c in connect if not c.startswith("tls/")]):
        print(
            f"splittag {command}: --certs with {plain[0]}: a TLS deployment listens on a tls/ endpoint", file=sys.stderr
        )
        return None
    if args.robot_id != "*":
        from shared.wire import keys

        try:
            keys.camera_pose(args.robot_id)
        except ValueError as exc:
            print(f"splittag {command}: {exc} (or '*' for every robot)", file=sys.stderr)
            return None
    return ZenohSettings(mode="client", connect=connect, tls=tls, connect_timeout_secs=5.0)


def _cmd_watch(args: argparse.Namespace) -> int:
    from shared.tools.watch import key_for, watch

    if args.format == "tum" and args.topic != "poses":
        print("splittag watch: --format tum is for poses", file=sys.stderr)
        return 2
    if args.format == "tum" and args.robot_id == "*":
        print("splittag watch: --format tum is one robot's trajectory: name it (--robot-id)", file=sys.stderr)
        return 2
    if args.count is not None and args.count < 1:  # (--duration: its parser type)
        print("splittag watch: --count must be positive", file=sys.stderr)
        return 2
    settings = _reader_settings(args, "watch")
    if settings is None:
        return 2
    import os
    import signal
    import time

    first: list[float] = []

    def on_term(signum: int, _frame: object) -> None:  # `timeout`, a supervisor: end as Ctrl-C does, with the summary
        # Once: a second signal while the watch closes its session (`timeout` and its child both signalled)
        # was a KeyboardInterrupt traceback out of session.close() instead of the summary. One more, 2 s
        # later, ends it at once (a close that hangs must not make it unstoppable: review).
        now = time.monotonic()
        if not first:
            first.append(now)
            raise KeyboardInterrupt
        if now - first[0] >= 2.0:
            os._exit(128 + signum)

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    result = watch(
        args.topic,
        args.robot_id,
        settings,
        fmt=args.format,
        count=args.count,
        duration_secs=args.duration,
        wait_secs=args.wait_secs,
    )
    print(result.summary(key_for(args.topic, args.robot_id)), file=sys.stderr)
    if first:  # stopped by a signal: a second one now would kill the interpreter as it exits (exit -2)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return 0 if result.messages else 1


def _cmd_map(args: argparse.Namespace) -> int:
    from shared.tools.watch import get_map, json_line, map_text

    settings = _reader_settings(args, "map", steers=args.save)
    if settings is None:
        return 2
    if args.robot_id == "*" and args.save:
        print("splittag map: --save names one robot (slam refuses a save through a wildcard)", file=sys.stderr)
        return 2
    for tag_map in get_map(args.robot_id, settings, save=args.save):
        print(json_line(tag_map) if args.json else "\n".join(map_text(tag_map)))
    if args.save:  # slam answers a save only once its files are written
        print("saved: slam wrote map.json, slam.json and the trajectory into its run folder", file=sys.stderr)
    return 0


def _cmd_stats(args: argparse.Namespace) -> int:
    import json

    from shared.tools.watch import get_stats, stats_text

    settings = _reader_settings(args, "stats")
    if settings is None:
        return 2
    stats = get_stats(args.robot_id, settings)
    print(json.dumps(stats, indent=2) if args.json else "\n".join(stats_text(stats)))
    return 0


def _cmd_split(args: argparse.Namespace) -> int:
    from shared.transport.split_client import split_query

    k, codec, release = args.k, args.codec, args.action == "release"
    if args.action == "set" and k is None and codec is None:
        print("splittag split set: give k (0..7) and/or --codec", file=sys.stderr)
        return 2
    if args.action != "set" and (k is not None or codec is not None):
        print(f"splittag split {args.action}: k and --codec are for set", file=sys.stderr)
        return 2
    if args.action != "get" and args.robot_id == "*":  # robot_infer refuses a set through a wildcard
        print(f"splittag split {args.action}: names one robot (--robot-id), not '*'", file=sys.stderr)
        return 2
    if k is not None:  # said before reaching for the router: a bad k is the user's, not the network's
        from shared.wire.cuts import check_cut

        try:
            check_cut(k)
        except ValueError as exc:
            print(f"splittag split set: {exc}", file=sys.stderr)
            return 2
    settings = _reader_settings(args, "split", steers=args.action != "get")
    if settings is None:
        return 2
    print(split_query(args.robot_id, settings.connect, k=k, codec=codec, release=release, tls=settings.tls))
    return 0


def _cmd_echo(args: argparse.Namespace) -> int:
    from shared.tools import echo
    from shared.transport.session import ZenohSettings

    settings = ZenohSettings(mode="router", listen=args.listen, connect=args.connect, shared_memory=args.shared_memory)
    if args.cpus:
        from shared.runtime.cpus import CpuPlacementError, pin_cpus

        try:
            pin_cpus(args.cpus)
        except CpuPlacementError as exc:
            print(f"echo: --cpus {args.cpus}: {exc}", file=sys.stderr)
            return 2
    echo.run(settings, robot_id=args.robot_id)
    return 0


def _cmd_data_generate(args: argparse.Namespace) -> int:
    from shared.datasets.generate import SampleMaker, generate
    from shared.vision.geometry import camera_from_yaml, default_camera

    camera = camera_from_yaml(args.camera) if args.camera else default_camera()
    maker: SampleMaker
    if args.data_command == "synth":
        from shared.datasets.synth import BLURRED_SMALL_TAGS, FIRST_DATA_SETS, SynthMaker, SynthSettings

        preset = {"first": FIRST_DATA_SETS, "blurred-small": BLURRED_SMALL_TAGS}.get(args.generator, {})
        from pydantic import ValidationError

        tone = {"tone_exponent": tuple(args.tone_exponent)} if args.tone_exponent else {}
        try:
            synth = SynthSettings(seed=args.seed, **{**preset, **tone})
        except ValidationError as exc:  # SynthSettings holds the rules (e.g. 0 < lo <= hi); say them plainly
            why = "; ".join(str(e["msg"]).removeprefix("Value error, ") for e in exc.errors(include_url=False))
            raise SystemExit(f"splittag data synth: bad --tone-exponent LO HI or preset: {why}") from None
        settings, maker, shard_size = synth.model_dump(mode="json"), SynthMaker(camera, synth), 250
    else:
        from shared.datasets.render import RenderMaker, RenderSettings

        render = RenderSettings(seed=args.seed)
        settings, maker, shard_size = render.model_dump(mode="json"), RenderMaker(camera, render), 200
    info = generate(
        args.out,
        n=args.n,
        seed=args.seed,
        kind=args.data_command,
        settings={"camera": camera.model_dump(), **settings},
        maker=maker,
        workers=args.workers,
        shard_size=shard_size,
    )
    _print_info(info)
    return 0


def _print_info(info: dict[str, Any]) -> None:
    c = info["counts"]
    print(
        f"{info['kind']}: {c['samples']} samples ({c['train']} train / {c['test']} test), "
        f"{c['attempts']} attempts, stage-1 failure rate {100 * c['detector_failure_rate']:.2f} %, "
        f"{info['last_run']['wall_secs']} s this run"
    )
    for key in ("failure_by_distance_m", "failure_by_tilt_deg"):
        cells = [f"{r['range'][0]}-{r['range'][1] or 'inf'}: {r['failures']}/{r['attempts']}" for r in info[key]]
        print(f"  {key}: " + ", ".join(cells))


def _cmd_data_show(args: argparse.Namespace) -> int:
    import numpy as np

    from shared.datasets.shards import load_dataset
    from shared.datasets.sheet import contact_sheet, write_sheet

    ds = load_dataset(args.dir)
    rows = np.random.default_rng(args.seed).choice(len(ds), size=min(args.n, len(ds)), replace=False)
    a = ds.arrays
    labels = [f"id {a['tag_id'][i]} {a['distance_m'][i]:.1f}m {a['tilt_deg'][i]:.0f}deg" for i in rows]
    write_sheet(args.out, contact_sheet(a["roi"][rows], a["keypoints"][rows], labels=labels))
    print(f"wrote {args.out}")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from shared.training.train import train

    settings = model_from_args(TrainSettings, args)
    result = train(settings)
    print(f"best test e_px {result['best_e_px']:.3f} px; weights in {args.out / 'best'}")
    return 0


def _cmd_quantize(args: argparse.Namespace) -> int:
    import json

    from shared.training.quantize import quantize

    print(json.dumps(quantize(model_from_args(QuantizeSettings, args)), indent=2))
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    import json

    from shared.model.export import export

    cuts = tuple(sorted(set(args.ks))) if args.ks else tuple(range(N_CUTS))
    calibration = evaluation = None
    source = ""
    int8_onnx = args.format == "onnx" and args.precision == "int8"
    int8_only = {"--calibration-data": args.calibration_data, "--calibration-samples": args.calibration_samples}
    int8_only["--evaluation-samples"] = args.evaluation_samples
    if not int8_onnx and (given := [name for name, value in int8_only.items() if value is not None]):
        print(f"splittag export: {', '.join(given)}: for --format onnx --precision int8 only", file=sys.stderr)
        return 2
    n_calibration = 300 if args.calibration_samples is None else args.calibration_samples
    n_evaluation = 200 if args.evaluation_samples is None else args.evaluation_samples
    if int8_onnx:
        print("quantising for ONNX Runtime: calibration and a check on held-out ROIs (about two minutes)", flush=True)
        if args.calibration_data is not None:
            from shared.datasets.shards import load_dataset

            data = load_dataset(args.calibration_data)
            calibration = data.arrays["roi"][data.split("train")[:n_calibration]]
            test = data.split("test")[:n_evaluation]
            evaluation = (data.arrays["roi"][test], data.arrays["keypoints"][test])
            source = f"{args.calibration_data}: its train split (checked on its test split)"
        else:
            from shared.datasets.synth import CALIBRATION_SEED, EVALUATION_SEED, mixed_rois

            calibration, _ = mixed_rois(n_calibration, CALIBRATION_SEED)
            if n_evaluation > 0:
                evaluation = mixed_rois(n_evaluation, EVALUATION_SEED)
            source = (
                "the training generator (`splittag data synth`), a third each: its default settings, small far "
                "tags in heavy blur with sRGB-like tone curves, and the default settings with those tone curves "
                "(shared.datasets.synth.TRAINING_MIX), at seeds "
                f"{CALIBRATION_SEED} + 100 i (checked at {EVALUATION_SEED} + 100 i)"
            )
    from shared.model.export import stale_export_files

    held = stale_export_files(args.out) if args.out.is_dir() else []
    manifest = export(
        args.weights,
        args.out,
        fmt=args.format,
        precision=args.precision,
        cuts=cuts,
        calibration=calibration,
        evaluation=evaluation,
        calibration_source=source,
    )
    doc = json.loads(manifest.read_text())
    replaced = f" (replacing the {len(held)} files of the export it held)" if held else ""
    print(f"wrote {len(doc['files'])} graphs for k = {', '.join(map(str, cuts))} and {manifest}{replaced}")
    if "accuracy" in doc:
        a = doc["accuracy"]
        print(
            f"int8 on {a['samples']} held-out ROIs: e_px {a['e_px_fp32']:.4f} -> {a['e_px_int8']:.4f} px "
            f"({a['e_px_change']:+.4f}); keypoints moved {a['moved_px_mean']:.4f} px mean, {a['moved_px_p99']:.4f} p99"
        )
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    import json

    from shared.datasets.shards import load_dataset
    from shared.model.net import SplitKeypointNet
    from shared.model.runtime import SplitNet, TorchSplitNet, load_split_net
    from shared.model.views import with_views
    from shared.model.weights import load_model
    from shared.training.evaluate import evaluate, format_report

    model = load_model(args.weights)
    if args.calibrate_fusion:
        from shared.model.weights import write_keypoint_fusion
        from shared.training.evaluate import calibrate_fusion

        fusion = calibrate_fusion(
            model, load_dataset(args.data), split=args.split, limit=args.limit, command=shlex.join(sys.argv[1:])
        )
        write_keypoint_fusion(args.weights, fusion)
        print(f"wrote keypoint_fusion to {args.weights}/config.json: {fusion.model_dump_json()}")
        return 0
    net: SplitKeypointNet | SplitNet = (
        model if args.precision == "fp32" else load_split_net(args.weights, args.precision)
    )
    if args.views > 1:
        net = with_views(TorchSplitNet(model, bf16=False) if isinstance(net, SplitKeypointNet) else net, args.views)
    result = evaluate(net, load_dataset(args.data), split=args.split, limit=args.limit)
    result["precision"] = args.precision
    result["views"] = args.views
    print(format_report(result))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
        print(f"wrote {args.json}")
    return 0


def _cmd_detect(args: argparse.Namespace) -> int:
    from shared.tools.detect import run_detect

    return run_detect(
        args.paths,
        camera_path=args.camera,
        tag_size_m=args.tag_size,
        tags_path=args.tags,
        weights=args.weights,
        json_path=args.json,
        quad_decimate=args.quad_decimate,
        aruco=not args.no_aruco,
        lines=not args.no_lines,
        soft_decode=args.soft_decode,
        views=args.views,
    )


def _cmd_profile(args: argparse.Namespace) -> int:
    import torch

    from shared.model.net import SplitKeypointNet
    from shared.model.profile import profile_cuts
    from shared.model.weights import load_model
    from shared.runtime.cpus import cpu_label
    from shared.wire.cuts import CUTS

    print(f"CPU: {cpu_label()}", flush=True)  # (README: every benchmark prints its CPU first)
    torch.set_num_threads(args.threads)
    model = load_model(args.weights) if args.weights.exists() else SplitKeypointNet(roi_margin=0.2)
    timings = profile_cuts(model, variant=args.variant, batch=args.batch, repetitions=args.repetitions)
    print(
        f"payload S(k) and cumulative robot compute C(k); {args.variant}, {args.threads} thread(s), "
        f"batch {args.batch}, median of {args.repetitions}"
    )
    print(f"{'k':>2} {'split point':<12} {'S(k) kB':>9} {'C(k) ms':>9}")
    for cut, t in zip(CUTS, timings, strict=True):
        print(f"{cut.k:>2} {cut.name:<12} {cut.tensor_bytes() / 1024:>9.2f} {t.median_ms:>9.2f}")
    return 0


def _cmd_link_up(args: argparse.Namespace) -> int:
    import threading

    from shared.runtime.signals import SignalStop
    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings, profile

    emu = LinkEmulator(LinkEmulatorSettings(prefix=args.prefix))
    emu.up(profile(args.profile))
    s = emu.settings
    print(
        f"link up: robot netns {s.robot_ns} ({s.robot_addr}), edge netns {s.edge_ns} ({s.edge_addr}, "
        f"reachable from here at {s.mgmt_edge_addr}); profile {args.profile}. "
        f"Switch with `splittag link set PROFILE`; Ctrl-C tears it down.",
        flush=True,
    )
    stop = threading.Event()
    SignalStop(stop)
    # Until Ctrl-C, or until the link is gone under it (`link down`, the delay line killed): then it
    # says so and ends, rather than claim a link that is not there (a trial's kept running).
    while not stop.wait(0.5):
        if not stop.is_set() and not emu.is_up():  # (Ctrl-C also reaches the `ip` child it runs)
            print(
                f"splittag link up: the emulated link with prefix {s.prefix!r} was removed by another process "
                "(`splittag link down`?) or its delay line died; ending",
                file=sys.stderr,
                flush=True,
            )
            emu.down()
            return 1
    emu.down()
    return 0


def _cmd_link_set(args: argparse.Namespace) -> int:
    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings, profile

    chosen = profile(args.profile)  # an unknown name: LinkProfileError, one line (exit 2)
    try:
        LinkEmulator(LinkEmulatorSettings(prefix=args.prefix)).set_profile(chosen)
    except (RuntimeError, OSError, ValueError) as exc:  # LinkEmulationUnavailable is a RuntimeError
        # not up, a tc call refused, the delay line gone or answering nonsense: one line
        print(f"splittag link set: {exc}", file=sys.stderr)
        return 1
    print(f"link profile {args.profile}")
    return 0


def _cmd_link_down(args: argparse.Namespace) -> int:
    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings

    emu = LinkEmulator(LinkEmulatorSettings(prefix=args.prefix))
    inside = emu.services_inside()
    if inside and not args.force:  # (a trial's `link down` blinded a running demo, and nothing said so)
        print(
            f"splittag link down: the link is in use by a running deployment (pids {' '.join(map(str, inside))}): "
            "stop it first (`splittag down`: its launcher removes the link), or --force",
            file=sys.stderr,
        )
        return 1
    was_up = emu.is_up()
    emu.down()
    print(f"link {args.prefix} down" if was_up else f"no emulated link with prefix {args.prefix!r} was up")
    return 0


def _probe_here(args: argparse.Namespace) -> list[list[float]]:
    from shared.tools.linkprobe import probe_payloads, run_probes
    from shared.transport.probe import Prober
    from shared.transport.session import ZenohSettings, open_session
    from shared.wire import keys

    session = open_session(ZenohSettings(mode="client", connect=[args.connect]))
    try:
        _wait_for_an_echo(session, args.robot_id, args.connect, args.wait_secs)
        prober = Prober(session, keys.echo(args.robot_id))
        try:
            return run_probes(prober, probe_payloads(args.tags), repetitions=args.repetitions)
        finally:
            prober.close()
    finally:
        session.close()


def _wait_for_an_echo(session: Any, robot_id: str, endpoint: str, timeout_secs: float = 30.0) -> None:
    """Until an echo for `robot_id` is up behind `endpoint`: `splittag echo`'s, or a running deployment's
    edge_infer, which serves one (a two-host trial's probe of its running edge waited for the echo's token
    alone and ended in a traceback). ReaderError in one line when neither comes."""
    import threading

    from shared.tools.watch import ReaderError
    from shared.wire import keys

    up = threading.Event()
    subs = [
        session.liveliness().declare_subscriber(keys.alive(robot_id, who), lambda _s: up.set(), history=True)
        for who in ("echo", "edge_infer")
    ]
    try:
        if not up.wait(timeout_secs):
            raise ReaderError(
                f"no echo for {robot_id} behind {endpoint} within {timeout_secs:g} s: is edge_infer (a deployment's "
                "edge) or `splittag echo` running there, for this --robot-id?"
            )
    finally:
        for sub in subs:
            sub.undeclare()


def _probe_emulated(args: argparse.Namespace) -> list[list[float]]:
    import json
    import subprocess
    import sys
    import tempfile

    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings, in_netns, profile

    emu_settings = LinkEmulatorSettings(prefix=args.prefix)
    endpoint = f"tcp/{emu_settings.edge_addr}:{EDGE_PORT}"
    with tempfile.TemporaryDirectory() as tmp, LinkEmulator(emu_settings, log_dir=Path(tmp)) as emu:
        emu.up(profile(args.profile))
        py = [sys.executable, "-m", "shared.tools.cli"]
        echo = subprocess.Popen(
            in_netns(emu_settings.edge_ns, [*py, "echo", "--listen", endpoint, "--robot-id", args.robot_id]),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        try:
            raw = Path(tmp) / "samples.json"
            probe = [*py, "link", "probe", "--connect", endpoint, "--robot-id", args.robot_id]
            probe += ["--repetitions", str(args.repetitions), "--tags", str(args.tags), "--samples-out", str(raw)]
            subprocess.run(in_netns(emu_settings.robot_ns, probe), check=True, timeout=3600)
            samples: list[list[float]] = json.loads(raw.read_text())
            return samples
        finally:
            echo.terminate()
            echo.wait(timeout=10)


def _cmd_link_probe(args: argparse.Namespace) -> int:
    import json

    from shared.tools.linkprobe import plot_link, report

    samples = _probe_emulated(args) if args.profile else _probe_here(args)
    if args.samples_out:
        args.samples_out.write_text(json.dumps(samples))
        return 0
    config = None
    if args.profile:
        from shared.tools.linkemu import profile

        link = profile(args.profile)
        config = {"rate_mbit": link.rate_mbit, "delay_ms": link.delay_ms, "beta_ms_per_kB": link.beta_ms_per_kB}
    doc = report(samples, profile=args.profile, profile_config=config, repetitions=args.repetitions, tags=args.tags)
    print(
        f"t0 {doc['t0_ms']:.2f} ms (fitted intercept), floor {doc['floor_ms']:.2f} ms (measured), "
        f"beta {doc['beta_ms_per_kB']:.4f} ms/kB (kB = 1024 bytes), rmse {doc['rmse_ms']:.2f} ms over {doc['n']} probes"
        + (
            f"; configured: floor {config['delay_ms']:g} ms, beta {config['beta_ms_per_kB']:.4f} ms/kB"
            if config
            else ""
        )
    )
    for m in doc["per_size"]:
        print(f"  {m['payload_kB']:>9.2f} kB  median {m['rtt_ms_median']:8.2f} ms  p90 {m['rtt_ms_p90']:8.2f} ms")
    _write_outputs(args, doc, plot_link)
    return 0


def _cmd_link_cost(args: argparse.Namespace) -> int:
    import json

    import torch

    from shared.control.compute import head_per_tag_ms, tail_per_tag_ms
    from shared.model.profile import calibrate_pnp_ms
    from shared.model.runtime import calibrate_cumulative_ms, calibrate_tail_ms, load_split_net
    from shared.runtime.cpus import cpu_label
    from shared.tools.linkprobe import cost_table, link_fit_of, plot_costs
    from shared.wire.cuts import CUTS, tensor_bytes

    print(f"CPU: {cpu_label()}", flush=True)  # C(k) and E(k) are this CPU's
    torch.set_num_threads(args.threads)
    fit = link_fit_of(json.loads(args.link.read_text()))
    net = load_split_net(args.weights, args.precision, threads=args.threads)
    # Each cut's head is timed `repetitions` times, the cuts taking turns, and its fastest run kept
    # (calibrate_cumulative_ms); then the services' bound (a head cannot be cheaper than an earlier cut's):
    # a trial under load read C(5) 69.6, C(6) 55.9, C(7) 71.1 ms and a starred k = 6 that was noise.
    raw = calibrate_cumulative_ms(net, repetitions=args.repetitions)
    compute = [args.stage1_ms + args.tags * c for c in head_per_tag_ms(raw)]
    compute_raw = [args.stage1_ms + args.tags * c for c in raw]
    edge: list[float] | None = None
    if not args.paper:
        pnp = calibrate_pnp_ms()
        tails = calibrate_tail_ms(net, repetitions=args.repetitions)
        edge = [args.tags * t for t in tail_per_tag_ms(tails, pnp)]
    payload = [args.tags * tensor_bytes(c.k, "fp16") / 1024 for c in CUTS]
    table = cost_table(
        compute_ms=compute, edge_ms=edge, payload_kB=payload, fit=fit, gammas=args.gamma, paper=args.paper
    )
    table.update(
        {
            "precision": net.precision,
            "tags": args.tags,
            "stage1_ms": args.stage1_ms,
            "repetitions": args.repetitions,
            "C_measured_ms": [compute_raw[k] for k in table["k"]],
            "cpu": cpu_label(),
        }
    )
    print(
        f"model: {table['model']}"
        + (
            "; no raw-ROI cut and no edge compute, as the paper (without --paper: splittag's model, with k = 0 "
            "and E(k))"
            if args.paper
            else "; k = 0 sends the raw ROI, E(k) is the edge's rest of the network + PnP (--paper: the paper's "
            "Eq. 4, k = 1..7 without E(k))"
        )
    )
    print(
        f"link: t0 {fit.t0_ms:.2f} ms, beta {fit.beta_ms_per_kB:.4f} ms/kB (kB = 1024 bytes); {args.tags} tag(s); "
        f"network at {net.precision}, {args.threads} thread(s), this CPU"
        + ("" if args.paper else "; edge as fast as gamma=1")
    )
    print(
        "C(k): stage 1 "
        + (f"{args.stage1_ms:g} ms" if args.stage1_ms else "NOT included (--stage1-ms adds it)")
        + f" + the network's head up to k, the fastest of {args.repetitions} runs per cut with the cuts taking "
        "turns, then kept from falling with k (C measured: before that bound); robot_infer's ComputeProfile (what "
        "the controller uses) includes its stage 1, which gamma slows as well"
    )
    # (a bound within 5 % of the timing is noise between nearly equal heads; beyond it, say so)
    lowered = [k for i, k in enumerate(table["k"]) if table["C_ms"][i] < 0.95 * table["C_measured_ms"][i]]
    if lowered:
        print(
            f"note: the bound lowered C(k) at k = {', '.join(map(str, lowered))} by over 5 % to a later cut's time: "
            "their "
            "timings were slower than a longer head's (load on this machine?); more --repetitions, or a quieter "
            "machine, measures them apart"
        )
    print(
        f"{'k':>2} {'split point':<10} {'S kB':>8} {'C ms':>7} {'C meas':>7}"
        + ("" if args.paper else f" {'E ms':>7}")
        + "".join(f"{'T g=' + format(r['gamma'], 'g'):>10}" for r in table["gammas"])
    )
    for i, k in enumerate(table["k"]):
        stars = "".join(f"{row['T_ms'][i]:>9.1f}{'*' if row['best_k'] == k else ' '}" for row in table["gammas"])
        e = "" if table["E_ms"] is None else f" {table['E_ms'][i]:>7.1f}"
        print(
            f"{k:>2} {table['split_point'][i]:<10} {table['S_kB'][i]:>8.1f} {table['C_ms'][i]:>7.1f} "
            f"{table['C_measured_ms'][i]:>7.1f}{e}{stars}"
        )
    _write_outputs(args, table, plot_costs)
    return 0


def _write_outputs(args: argparse.Namespace, doc: dict[str, Any], plot: Callable[[dict[str, Any], Path], None]) -> None:
    """--json and --plot of the link commands."""
    from shared.tools.linkprobe import write_json

    if args.json:
        write_json(doc, args.json)
    if args.plot:
        plot(doc, args.plot)
        print(f"figure: {args.plot}")


def _launch_extra(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """The config tables --fps, --gamma and --split-k set (over the config file's, into the run's config.toml)."""
    extra: dict[str, dict[str, Any]] = {}
    if args.fps is not None:
        extra.setdefault("camera", {})["fps"] = args.fps
    if args.gamma is not None:
        extra.setdefault("robot_infer", {})["gamma"] = args.gamma
    if args.split_k is not None:
        extra.setdefault("robot_infer", {})["split_k"] = args.split_k
    return extra


def _number_above(floor: float, *, inclusive: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number > floor (>= with `inclusive`), refused at once with the
    parser's own message (a trial's --fps 0 and --gamma 0.5 started every service, then failed)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        ok = value >= floor if inclusive else value > floor
        if not math.isfinite(value) or not ok:
            raise argparse.ArgumentTypeError(f"{text} must be {'>=' if inclusive else '>'} {floor:g}")
        return value

    return parse


POSITIVE = _number_above(0.0)


def _count_from(floor: int) -> Callable[[str], int]:
    """An argparse type: a whole number >= floor, refused with the parser's own message."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < floor:
            raise argparse.ArgumentTypeError(f"{text} must be >= {floor}")
        return value

    return parse


_positive_int, _non_negative_int = _count_from(1), _count_from(0)


def _add_launch_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--controller", action="store_true", help="also run the adaptive split controller")
    p.add_argument("--fps", type=POSITIVE, default=None, help="the camera's rate (camera.fps; the config's otherwise)")
    p.add_argument(
        "--gamma",
        type=_number_above(1.0, inclusive=True),
        default=None,
        help="emulate a robot CPU this many times slower than this one: robot_infer's compute x gamma "
        "(robot_infer.gamma, >= 1 here; a gamma < 1 needs robot_infer.emulated_ms_per_tag_by_k, set both in "
        "the config; the paper's gamma in T(k) = gamma C(k) + t0 + beta S(k))",
    )
    p.add_argument("--split-k", type=int, choices=range(8), default=None, help="the cut at start (robot_infer.split_k)")
    p.add_argument(
        "--link",
        metavar="PROFILE",
        help="run robot and edge sides over the emulated uplink (root): 5g, 5g-pre-tdd, ...",
    )
    p.add_argument(
        "--link-profiles",
        type=Path,
        metavar="TOML",
        help="extra link profiles for --link ([name] rate_mbit, delay_ms, description)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(prog="splittag", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    _add_deploy_commands(sub)
    _add_control_commands(sub)
    _add_link_commands(sub)
    _add_data_commands(sub)
    _add_model_commands(sub)
    return parser


def _add_deploy_commands(sub: Any) -> None:
    """demo, up, down: run the services."""
    p = sub.add_parser("demo", help="run the whole pipeline on the demo scene with a live line per second")
    p.add_argument("--config", type=Path, default=Path("deploy/local.toml"))
    p.add_argument("--duration", type=POSITIVE, default=30.0)
    _add_launch_options(p)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("up", help="start every service (deploy/up.sh); Ctrl-C stops them")
    p.add_argument("--config", type=Path, default=Path("deploy/local.toml"))
    p.add_argument("--duration", type=POSITIVE, default=None, help="stop after this many seconds")
    p.add_argument("--runs", type=Path, default=Path("runs"), help="run folders go under here (RUNS/current links)")
    p.add_argument(
        "--only",
        choices=["edge", "robot"],
        default=None,
        help="this host's part of a two-host deployment: edge (edge_infer, slam) or robot (camera, robot_infer, "
        "and the controller with --controller); run the other part on the other host with the same config",
    )
    _add_launch_options(p)
    p.set_defaults(func=_cmd_up)
    p = sub.add_parser("fleet", help="N robots and M edge workers with one slam (deploy/fleet.toml); Ctrl-C stops")
    p.add_argument("--config", type=Path, default=Path("deploy/fleet.toml"))
    p.add_argument("--duration", type=POSITIVE, default=None, help="stop after this many seconds")
    p.add_argument("--runs", type=Path, default=Path("runs"), help="run folders go under here (RUNS/current links)")
    p.add_argument("--only", default=None, help="'edge' (slam + workers) or one robot id: this host's part")
    p.add_argument(
        "--make-certs",
        action="store_true",
        help="issue a certificate per process into the [fleet] certs folder (a new CA if it has none), then exit",
    )
    p.set_defaults(func=_cmd_fleet)

    p = sub.add_parser(
        "down",
        help="stop the deployment in RUNS/current through its launcher; if the launcher had died, stop its "
        "services and finish the run (summary.json, merged recording)",
    )
    p.add_argument("--runs", type=Path, default=Path("runs"), help="the runs folder (RUNS/current is stopped)")
    p.set_defaults(func=_cmd_down)


def _add_control_commands(sub: Any) -> None:
    """split, echo: steer and serve a running deployment."""
    p = sub.add_parser("split", help="read or set the split index live (Zenoh query)")
    p.add_argument("action", choices=["get", "set", "release"])
    p.add_argument("k", type=int, nargs="?", help="split index 0..7 (for set)")
    p.add_argument("--codec", choices=["fp16", "fp32"], help="set: how cuts 1..6 travel (with or without k)")
    _add_reader_options(p, robot_help="the robot's id (get: '*' reads every robot's)")
    p.set_defaults(func=_cmd_split)

    p = sub.add_parser("watch", help="print what a running deployment publishes: poses, tags, controller, map")
    p.add_argument("topic", choices=["poses", "tags", "controller", "map"])
    p.add_argument(
        "--format",
        choices=["text", "json", "tum"],
        default="text",
        help="json: one object per line; tum: tracking poses as TUM lines, stamped as trajectory.tum is",
    )
    p.add_argument("--count", type=int, default=None, help="stop after this many messages")
    p.add_argument("--duration", type=POSITIVE, default=None, help="stop after this many seconds")
    p.add_argument(
        "--wait-secs",
        type=float,
        default=30.0,
        help="with no router in reach yet, keep trying this long (a watch started before `splittag up`)",
    )
    _add_reader_options(p)
    p.set_defaults(func=_cmd_watch)

    p = sub.add_parser("map", help="the tag map slam holds now (a get on its map queryable)")
    p.add_argument(
        "--json",
        action="store_true",
        help="the TagMap message as one JSON object (map.json in the run folder is the tag-map file slam loads)",
    )
    p.add_argument("--save", action="store_true", help="also have slam write map.json and the trajectory now")
    _add_reader_options(p)
    p.set_defaults(func=_cmd_map)

    p = sub.add_parser("stats", help="every running service's input counters (accepted, refused by reason)")
    p.add_argument("--json", action="store_true", help="the replies as one JSON object, by the key that answered")
    _add_reader_options(p)
    p.set_defaults(func=_cmd_stats)

    p = sub.add_parser("echo", help="run the edge echo queryable for link probes")
    p.add_argument("--robot-id", default="robot1")
    p.add_argument("--listen", action="append", default=[], help="zenoh endpoint, repeatable")
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint, repeatable")
    p.add_argument("--shared-memory", action="store_true", help="zenoh shared memory on (same host, no shaping)")
    p.add_argument("--cpus", type=int, nargs="+", help="run on these CPUs only (an edge sharing the robot's host)")
    p.set_defaults(func=_cmd_echo)


def _add_reader_options(p: argparse.ArgumentParser, robot_help: str = "the robot's id, or '*' for every robot") -> None:
    """Where a command that reads or steers a running deployment connects, and as whom."""
    p.add_argument("--robot-id", default="robot1", help=robot_help)
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        help=f"zenoh endpoint to connect to (default {Topology().edge_router}, tls/ with --certs); again for a "
        "second one, used while the first is away (the robot's router, tcp/<robot>:7448)",
    )
    p.add_argument("--certs", type=Path, help="TLS deployments: the certificates folder (deploy/make-certs.sh)")
    p.add_argument("--identity", default="operator", help="TLS deployments: whose certificate to present")


def _add_link_commands(sub: Any) -> None:
    """link up/set/down/probe/cost: the emulated uplink and what it costs."""
    link_parser = sub.add_parser("link", help="emulated 5G uplink, link probing and split costs")
    link_parser.add_argument(
        "--profiles", type=Path, help="TOML of extra link profiles ([name] rate_mbit, delay_ms, description)"
    )
    link = link_parser.add_subparsers(dest="link_command", required=True)
    p = link.add_parser("up", help="create the robot/edge namespaces with the emulated link (root); Ctrl-C removes")
    p.add_argument("--profile", default="5g")
    p.add_argument("--prefix", default="st")
    p.set_defaults(func=_cmd_link_up)
    p = link.add_parser("set", help="switch the running emulated link to another profile")
    p.add_argument("profile")
    p.add_argument("--prefix", default="st")
    p.set_defaults(func=_cmd_link_set)
    p = link.add_parser("down", help="remove the emulated link (not while a deployment uses it)")
    p.add_argument("--prefix", default="st")
    p.add_argument("--force", action="store_true", help="remove it even while a deployment's processes use it")
    p.set_defaults(func=_cmd_link_down)
    p = link.add_parser("probe", help="fit RTT = t0 + beta*S from probes at every split point's payload")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--profile", help="probe a fresh emulated link with this profile (root)")
    where.add_argument(
        "--connect",
        default=Topology().edge_router,
        help="or probe the echo behind this endpoint (a deployment's edge_infer, or `splittag echo`)",
    )
    p.add_argument("--prefix", default="st")
    p.add_argument("--robot-id", default="robot1")
    p.add_argument("--wait-secs", type=float, default=30.0, help="how long to wait for the echo (--connect)")
    p.add_argument("--repetitions", type=int, default=200)
    p.add_argument("--tags", type=int, default=1, help="payloads of this many tags per split point")
    p.add_argument("--json", type=Path)
    p.add_argument("--plot", type=Path)
    p.add_argument("--samples-out", type=Path, help=argparse.SUPPRESS)
    p.set_defaults(func=_cmd_link_probe)
    p = link.add_parser("cost", help="T(k) per split point for several gamma from measured C, E and a fitted link")
    p.add_argument("--link", type=Path, required=True, help="JSON written by `splittag link probe`")
    p.add_argument(
        "--gamma",
        type=float,
        nargs="+",
        default=[1.0, 2.0, 4.0, 8.0],
        help="robot CPUs this many times slower than this one (the edge stays this CPU)",
    )
    p.add_argument("--tags", type=int, default=1, help="tags per frame (payload and compute scale with it)")
    p.add_argument(
        "--paper",
        action="store_true",
        help="the paper's Eq. 4 exactly: T(k) = gamma C(k) + t0 + beta S(k) over k = 1..7 (no raw-ROI cut k = 0, "
        "no edge compute E(k)); default: splittag's model, k = 0..7 with E(k), as the controller predicts",
    )
    p.add_argument(
        "--stage1-ms",
        type=float,
        default=0.0,
        help="the robot's stage 1 per frame on this CPU, added to C(k) at every k (robot_infer's log and "
        "ComputeProfile say it; 0: the network alone)",
    )
    p.add_argument("--weights", type=Path, default=Path("models"))
    p.add_argument(
        "--precision", choices=PRECISION_CHOICES, default="auto", help="the network's arithmetic (both sides)"
    )
    p.add_argument("--threads", type=int, default=1)
    p.add_argument(
        "--repetitions",
        type=_count_from(1),
        default=30,
        help="timed runs per cut, the cuts taking turns; each cut's fastest is kept (default 30)",
    )
    p.add_argument("--json", type=Path)
    p.add_argument("--plot", type=Path)
    p.set_defaults(func=_cmd_link_cost)


def _add_data_commands(sub: Any) -> None:
    """data synth/render/show: training data."""
    data = sub.add_parser("data", help="generate and inspect training data").add_subparsers(
        dest="data_command", required=True
    )
    p = data.add_parser("synth", help="synthetic planar-tag data set (paper IV-A2)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--n", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--generator",
        choices=["current", "first", "blurred-small"],
        default="current",
        help="first: the first data sets' settings (display-order degradations, all ROIs perturbed); "
        "blurred-small: small far tags with motion blur up to half their side, found by the product's "
        "stage 1 (AprilTag, ArUco, line quads), most of which AprilTag alone misses",
    )
    p.add_argument(
        "--tone-exponent",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="the camera tone curve's exponent range, log-uniform (default: 1/1.8 .. 1.8, what synth2 and "
        "synth3 were made with; an sRGB camera is ~1/2.2, which that range misses)",
    )
    p.add_argument("--camera", type=Path, help="ROS camera_info YAML (default: the paper's camera)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.set_defaults(func=_cmd_data_generate)
    p = data.add_parser("render", help="MuJoCo-rendered rooms (replaces the paper's Gazebo set)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--n", type=int, default=8_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--camera", type=Path, help="ROS camera_info YAML (default: the paper's camera)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.set_defaults(func=_cmd_data_generate)
    p = data.add_parser("show", help="contact sheet of ROIs with ground-truth keypoints")
    p.add_argument("dir", type=Path)
    p.add_argument("--n", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("sheet.png"))
    p.set_defaults(func=_cmd_data_show)


def _add_model_commands(sub: Any) -> None:
    """profile, train, eval, detect: the network."""
    p = sub.add_parser("profile", help="the paper's Table: payload S(k) and cumulative compute C(k) per cut")
    p.add_argument("--weights", type=Path, default=Path("models"))
    p.add_argument(
        "--variant", choices=["fp32", "fp32-channels-last", "bf16-channels-last"], default="bf16-channels-last"
    )
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--repetitions", type=int, default=30)
    p.set_defaults(func=_cmd_profile)

    p = sub.add_parser("train", help="train the keypoint network (resumes from OUT/last.pt)")
    add_model_options(p, TrainSettings)
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("quantize", help="int8 variant: quantisation-aware fine-tuning, OpenVINO IR (resumes)")
    add_model_options(p, QuantizeSettings)
    p.set_defaults(func=_cmd_quantize)

    p = sub.add_parser(
        "export",
        help="head and tail of every cut as ONNX or OpenVINO graphs, with a manifest",
        description="Write head_k (the robot's part up to cut k) and tail_k (the edge's rest) for each cut as "
        "standalone graphs, and manifest.json (each file's input and output, the files it needs, the ROI "
        "contract; for OpenVINO the compile settings). A half that starts at the image takes the uint8 ROI "
        "(N,1,256,256); the others take the float32 cut tensor. README *Exporting the network*.",
    )
    p.add_argument("--weights", type=Path, default=Path("models"), help="the weights folder (default: models)")
    p.add_argument("--out", type=Path, required=True, help="the folder to write (made if missing)")
    p.add_argument(
        "--format",
        choices=["onnx", "openvino"],
        default="onnx",
        help="onnx: self-contained .onnx files (ONNX Runtime, TensorRT, ...); openvino: IR .xml + .bin",
    )
    p.add_argument(
        "--precision",
        choices=["fp32", "int8"],
        default="fp32",
        help="int8: with openvino the weights folder's int8 variant (the services' own); with onnx quantised "
        "here for ONNX Runtime (calibrated, its cost measured into the manifest)",
    )
    p.add_argument(
        "--calibration-data",
        type=Path,
        help="onnx int8: a training data set (`splittag data synth`) to calibrate on (its train split) and "
        "check on (its test split); default: ROIs of the training generator at seeds no shipped set used",
    )
    p.add_argument("--calibration-samples", type=_positive_int, help="onnx int8: ROIs to calibrate on (default 300)")
    p.add_argument(
        "--evaluation-samples", type=_non_negative_int, help="onnx int8: held-out ROIs to check (default 200; 0: none)"
    )
    p.add_argument(
        "--ks", type=int, nargs="+", choices=range(N_CUTS), metavar="K", help="only these cuts (default: 0..7)"
    )
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser("settings", help="every setting of the services with its default and meaning")
    settings_doc.add_arguments(p)
    p.set_defaults(func=settings_doc.run)

    p = sub.add_parser("eval", help="keypoint and pose errors of weights on a data set split")
    p.add_argument("--weights", type=Path, required=True, help="weights folder (model.safetensors + config.json)")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--split", choices=["train", "test", "all"], default="test")
    p.add_argument("--json", type=Path)
    p.add_argument(
        "--precision", choices=PRECISIONS, default="fp32", help="fp32/bf16: PyTorch; int8: the OpenVINO variant"
    )
    p.add_argument("--limit", type=int, default=None)
    p.add_argument("--views", type=int, choices=VIEW_COUNTS, default=1, help=VIEWS_HELP)
    p.add_argument(
        "--calibrate-fusion",
        action="store_true",
        help="measure the keypoint and corner sigmas on this split and write them into the weights' config.json",
    )
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("detect", help="stage 1 + network + PnP on image files or folders")
    p.add_argument("paths", type=Path, nargs="+")
    p.add_argument(
        "--camera",
        type=Path,
        help="ROS camera_info YAML (without it: an assumed pinhole camera per image, said on stderr; the poses' "
        "distance and tilt then depend on that guess, the keypoints do not)",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--tag-size",
        type=POSITIVE,
        default=None,
        help="tag size in metres (black square side; without it or --tags: 0.16, said on stderr)",
    )
    g.add_argument("--tags", type=Path, default=None, help="tag map YAML/JSON with per-tag sizes")
    p.add_argument("--weights", type=Path, default=None, help="weights folder (default: models/)")
    p.add_argument("--json", type=Path, required=True)
    p.add_argument(
        "--quad-decimate",
        type=float,
        default=1.0,
        help="AprilTag's decimation (default 1: full resolution, for stills; the services run 2 for speed)",
    )
    p.add_argument("--no-aruco", action="store_true", help="stage 1 without the ArUco proposer")
    p.add_argument(
        "--no-lines", action="store_true", help="stage 1 without the line-quad proposer (finds occluded tags)"
    )
    p.add_argument(
        "--soft-decode",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the line quads also read tags whose bits blur or an occluder smeared (blind soft decode; on)",
    )
    p.add_argument("--views", type=int, choices=VIEW_COUNTS, default=1, help=VIEWS_HELP)
    p.set_defaults(func=_cmd_detect)


def _load_link_profiles(args: argparse.Namespace) -> None:
    path = getattr(args, "profiles", None) or getattr(args, "link_profiles", None)
    if path:
        from shared.tools.linkemu import load_profiles

        load_profiles(path)


def _endpoint_hint(args: argparse.Namespace, runs: Path = Path("runs")) -> str:
    """Where the deployment in runs/current listens, when a reader (split, watch, map, stats) could not
    connect elsewhere (under --link the edge's router is on the emulated link's address: a trial's
    `split get` without --connect only said that 127.0.0.1:7447 was unreachable)."""
    import tomllib

    if not hasattr(args, "identity"):  # not a reader: the launcher's own failure names its endpoints
        return ""
    import time

    tried = split_endpoint(args.connect, tls=bool(getattr(args, "certs", None)))
    hosts = {e.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]") for e in tried}
    local = all(h == "localhost" or h == "::1" or h.startswith("127.") for h in hosts)
    current = runs / "current"
    try:
        config = current / "config.toml"
        if not config.is_file():  # a fleet's run: its edge router is slam's (a trial was told nothing ran)
            config = current / "config_slam.toml"
        doc = tomllib.loads(config.read_text())
        written = config.stat().st_mtime
    except (OSError, ValueError):  # (a reader of another host's deployment: nothing to say about this one)
        return "; no deployment is running here (`splittag up` or `make demo` starts one)" if local else ""
    endpoints = [str(e) for e in doc.get("monitor", {}).get("connect", [])] or [
        str(e).replace("/0.0.0.0:", "/127.0.0.1:") for e in doc.get("slam", {}).get("zenoh", {}).get("listen", [])
    ]
    if not _run_is_live(current):  # (two trials were pointed at the address of a run that had ended)
        # (a run without a summary, written in the last two minutes, may be starting: its launcher has not
        # written its pid yet)
        starting = not (current / "summary.json").is_file() and time.time() - written < 120
        if starting or not (local or set(tried) & set(endpoints)):
            return ""
        return f"; no deployment is running here (the last one, {current.resolve().name}, has ended)"
    if not endpoints or set(tried) & set(endpoints):
        return ""
    return f"; the deployment in {runs}/current listens at {endpoints[0]} (--connect {endpoints[0]})"


def _certificate_hint(args: argparse.Namespace) -> str:
    """What is wrong with the certificates between a reader and a tls/ endpoint it could not connect to
    (zenoh only says it timed out: a trial's operator certificate from another CA), found as the
    services find it (`certificate_problem`); "" when nothing is, or the reader uses no certificates."""
    certs = getattr(args, "certs", None)
    if not certs or not hasattr(args, "identity"):
        return ""
    from shared.transport.session import TlsSettings, certificate_problem

    try:
        tls = TlsSettings.from_dir(certs, args.identity)
    except (OSError, ValueError):
        return ""
    for endpoint in split_endpoint(args.connect, tls=True):
        problem = certificate_problem(endpoint, tls)
        if problem is not None:
            return f"; {problem}"
    return ""


def _live_run_processes(run: Path) -> tuple[int | None, list[tuple[str, int]]]:
    """The run folder's launcher pid (None when it is gone) and its services (name, pid) still running.
    Only processes that are still ours: a pid written by a run that ended without removing its files
    (killed) may belong to anything by now."""
    try:
        pid: int | None = int((run / "launcher.pid").read_text())
    except (OSError, ValueError):
        pid = None
    if pid is not None and not (_running(pid) and any(s in _cmdline(pid) for s in ("splittag", "shared.tools"))):
        pid = None
    try:
        lines = (run / "pids").read_text().splitlines()
    except OSError:
        lines = []
    listed = [(f[0], int(f[1])) for line in lines if len(f := line.split()) == 2 and f[1].isdigit()]
    return pid, [(name, p) for name, p in listed if _running(p) and "services." in _cmdline(p)]


def _run_is_live(run: Path) -> bool:
    """Whether the run folder's launcher, or any of its services, still runs (as `splittag down` judges)."""
    pid, services = _live_run_processes(run)
    return pid is not None or bool(services)


# The commands a light client runs (README *Reading poses from your own process*): they, their errors
# included, import only zenoh, msgspec, msgpack, pydantic(-settings) and numpy (tests/test_watch.py).
LIGHT_COMMANDS: Final[tuple[str, ...]] = ("split", "watch", "map", "stats")


def _user_errors(command: str) -> tuple[tuple[type[BaseException], ...], tuple[type[BaseException], ...]]:
    """(what a user got wrong: exit 2, what the running system said: exit 1), each said in one line
    instead of a traceback (SPLITTAG_TRACEBACK=1 shows the traceback too). Anything else is a bug
    and keeps its traceback."""
    import tomllib

    import zenoh

    from shared.tools.watch import ReaderError
    from shared.transport.split_client import SplitQueryError

    if command in LIGHT_COMMANDS:
        return (FileNotFoundError,), (SplitQueryError, ReaderError, zenoh.ZError)
    from shared.datasets.shards import DatasetError
    from shared.runtime.settings import ConfigurationError
    from shared.tools.fleet import FleetConfigError
    from shared.tools.launch import LaunchError
    from shared.tools.linkemu import LinkEmulationUnavailable, LinkProfileError
    from shared.vision.geometry import CameraFileError
    from shared.vision.tagmap import TagMapError

    usage = (
        DatasetError,
        FleetConfigError,
        LinkProfileError,
        LinkEmulationUnavailable,
        ModelFileError,
        ConfigurationError,
        FileNotFoundError,
        tomllib.TOMLDecodeError,
        CameraFileError,
        TagMapError,
    )
    return usage, (SplitQueryError, ReaderError, LaunchError, zenoh.ZError)


def _stdout_closed() -> bool:
    """Whether stdout's reader has gone (a pipe whose read end is closed): what a BrokenPipeError then
    means. Flushing says so when output was still buffered; a pipe polled for writing says so when the
    write that failed was already flushed (`splittag watch ... | head`: a trial's traceback)."""
    import select

    try:
        sys.stdout.flush()
    except BrokenPipeError:
        return True
    except (OSError, ValueError):
        return False
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (OSError, ValueError):
        return False


def main(argv: Sequence[str] | None = None) -> int:
    """Parse arguments and run the chosen subcommand."""
    import logging
    import os

    from shared.runtime.errors import one_line_error

    args = build_parser().parse_args(argv)
    setup_logging(f"splittag-{args.command}")
    if "SPLITTAG_LOG_LEVEL" not in os.environ and args.command in LIGHT_COMMANDS:
        # A one-shot command at the prompt: its answer, not the session's start-up news.
        for name in ("zenoh", "shared.transport.session"):
            logging.getLogger(name).setLevel(logging.WARNING)
    try:
        _load_link_profiles(args)
        code: int = args.func(args)
    except BrokenPipeError:
        if _stdout_closed():
            # Our reader went away (`splittag settings | head`): no traceback, none at exit either, and the
            # exit code a shell gives a command killed by SIGPIPE. Any other broken pipe is an error.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 141
        raise
    except ModuleNotFoundError as exc:
        if os.environ.get("SPLITTAG_TRACEBACK") or args.command in LIGHT_COMMANDS:
            raise  # a light command needs nothing a light install lacks: this is a bug
        # A light install (README *Reading poses from your own process*) has what split, watch, map and
        # stats need; any other command needs the full one (a trial got two chained tracebacks).
        print(
            f"splittag {args.command}: {exc}: this command needs the full install (`make setup`, README Quick "
            f"start); a light install runs only {', '.join(LIGHT_COMMANDS)}",
            file=sys.stderr,
        )
        return 2
    except Exception as exc:
        usage, failed = _user_errors(args.command)  # imported only here: every command starts as fast as before
        from pydantic import ValidationError

        # Settings a user wrote (a *Settings model refused them), not a message a bug built wrongly.
        settings = isinstance(exc, ValidationError) and exc.title.endswith("Settings")
        if not (settings or isinstance(exc, usage + failed)) or os.environ.get("SPLITTAG_TRACEBACK"):
            raise
        what = "Zenoh: " if type(exc).__module__.startswith("zenoh") else ""
        hint = _certificate_hint(args) or _endpoint_hint(args) if what and "Unable to connect" in str(exc) else ""
        print(f"splittag {args.command}: {what}{one_line_error(exc)}{hint}", file=sys.stderr)
        return 2 if settings or isinstance(exc, usage) else int(getattr(exc, "exit_code", 1))
    return code


if __name__ == "__main__":
    raise SystemExit(main())
