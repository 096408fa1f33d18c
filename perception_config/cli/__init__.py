"""The `perception-config` command: one subcommand per job, heavy imports deferred to the job."""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import warnings
from pathlib import Path
from typing import Any

# Light imports only (numpy): each command imports the rest it needs.
from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION, DEFAULT_VALIDATE_EVERY
from ..rl.settings import TIME_MODES, EnvSettings
from ..util.stop_signals import StopRequested


def _add_dataset_args(parser: argparse.ArgumentParser, **kw: Any) -> None:
    """--dataset DIR and --no-depth (read the dataset as RGB-only: BopDataset(use_depth=False))."""
    parser.add_argument("--dataset", type=Path, required=True, **kw)
    parser.add_argument("--no-depth", dest="use_depth", action="store_false",
                        help="read the dataset as RGB-only (its depth images ignored): the actions and blocks that "
                             "need depth are left out")


def _cmd_synth(args: argparse.Namespace) -> int:
    from ..datasets.synthetic import generate

    generate(
        args.out,
        scenes=args.scenes,
        images_per_scene=args.images_per_scene,
        seed=args.seed,
        models_dir=args.models,
        progress=not args.quiet,
        depth=args.depth,
    )
    print(f"wrote BOP dataset {args.out}")
    return 0


def _cmd_bag_write(args: argparse.Namespace) -> int:
    from ..datasets.bag import write_bag

    n = write_bag(args.dataset, args.out, split=args.split, rate_hz=args.rate, progress=not args.quiet,
                  use_depth=args.use_depth)
    print(f"wrote {n} frames to {args.out}")
    return 0


def _cmd_bag_info(args: argparse.Namespace) -> int:
    from ..datasets.bag import bag_info

    info = bag_info(args.file)
    if args.json:
        import json

        print(json.dumps(info, indent=2))
        return 0
    for key, value in info.items():
        if key == "topics":
            print("topics:")
            for t in value:
                comp = f"  {t['compression']}-compressed" if t["compression"] != "none" else ""
                print(f"  {t['topic']:<48} {t['type']:<36} {t['count']:>6} msgs{comp}")
        elif key == "compression":
            print(f"compression: chunks {', '.join(value['chunk'])}; messages {', '.join(value['message'])}")
        elif key == "frame_topics":
            print("would read frames from:" + (f" ({value['layout']} layout)" if "layout" in value else ""))
            for role in ("color", "depth", "camera_info", "ground_truth", "frame_info"):
                shown = value.get(role) or ("none (RGB-only)" if role == "depth" else None)
                if shown:
                    print(f"  {role:<13} {shown}")
        elif key == "frame_topics_error":
            print(f"cannot choose the frame topics: {value}")
        elif key == "camera_layouts":
            print("complete camera layouts (pick one with read_bag(color_topic=, depth_topic=, camera_info_topic=)):")
            for lay in value:
                print(f"  {lay['driver']}: {lay['color']}, {lay['depth']}, {lay['camera_info']}")
        else:
            print(f"{key}: {value}")
    return 0


def _cmd_episodes_info(args: argparse.Namespace) -> int:
    from ..store.report import format_info, store_info

    info = store_info(args.store)
    if args.json:
        import json

        print(json.dumps(info, indent=2))
    else:
        print(format_info(info))
    return 0


def _cmd_episodes_export(args: argparse.Namespace) -> int:
    from ..store.report import export_table

    n = export_table(args.store, args.out, args.table)
    print(f"wrote {n} rows of {args.table} to {args.out}")
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from ..datasets.show import show_frame

    out = show_frame(args.dataset, args.out, scene_id=args.scene, im_id=args.image, split=args.split,
                     use_depth=args.use_depth)
    print(f"wrote {out}")
    return 0


def _one_core() -> None:
    """Benchmarks measure one core: pin the numeric libraries before they load."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _cmd_bench_blocks(args: argparse.Namespace) -> int:
    _one_core()
    from ..bench.blocks import bench_blocks, format_blocks
    from ..blocks.pipeline import load_pipeline
    from ..datasets.bop_json import save_json

    stats = bench_blocks(args.dataset, load_pipeline(args.pipeline), n_frames=args.frames, lam=args.noise_lambda,
                         split=args.split, progress=not args.quiet, use_depth=args.use_depth)
    save_json(args.out, stats)
    print(format_blocks(stats))
    print(f"wrote {args.out}")
    return 0


def _cmd_bench_convergence(args: argparse.Namespace) -> int:
    _one_core()
    from ..bench.blocks import convergence_table, format_convergence
    from ..blocks.pipeline import load_pipeline
    from ..datasets.bop_json import save_json

    lambdas = [float(x) for x in args.lambdas.split(",")]
    table = convergence_table(args.dataset, load_pipeline(args.pipeline), lambdas, n_frames=args.frames,
                              max_applications=args.applications, split=args.split, progress=not args.quiet,
                              use_depth=args.use_depth)
    save_json(args.out, table)
    print(format_convergence(table))
    print(f"wrote {args.out}")
    return 0


def _cmd_bench_real(args: argparse.Namespace) -> int:
    _one_core()
    from ..bench.real import bench_real, format_real, save_real
    from ..blocks.pipeline import load_pipeline

    result = bench_real(args.dataset, load_pipeline(args.pipeline), n_frames=args.frames, seeds=args.seeds,
                        lambdas=[float(x) for x in args.lambdas.split(",")], max_calls=args.calls,
                        min_visib=args.min_visib, seed=args.seed, split=args.split, progress=not args.quiet,
                        blocks=args.blocks.split(",") if args.blocks else None,
                        refiner_costs=not args.no_refiner_costs, use_depth=args.use_depth)
    paths = save_real(result, args.out)
    print(format_real(result))
    print(f"wrote {paths[0]} and {paths[1]}")
    return 0


def _cmd_blocks(args: argparse.Namespace) -> int:
    from ..blocks import load_all

    for name, cls in sorted(load_all().items()):
        print(f"{name}  ({cls.kind.value}; inputs: {', '.join(cls.inputs)})")
        doc = (cls.__doc__ or "").strip().splitlines()
        if doc:
            print(f"    {doc[0]}")
        for p in cls.params:
            rng = f" in {list(p.choices)}" if p.choices else (f" in [{p.low}, {p.high}]" if p.low is not None else "")
            print(f"    {p.name} = {p.default!r}{rng}  {p.doc}")
        if cls.score_names:
            print(f"    scores: {', '.join(cls.score_names)}")
    return 0


def _cmd_fit_score(args: argparse.Namespace) -> int:
    _one_core()
    from ..learning.pick_success_data import collect_step_rows, featurise, load_step_rows
    from ..learning.pick_success_fit import fit_score, format_metrics

    if args.store is None and args.dataset is None:
        raise ValueError("give --store DB (learn from stored episodes) or --dataset DIR (play episodes)")
    if args.store is not None:
        rows = load_step_rows(args.store)
        source = {"store": str(args.store), "rows": len(rows)}
    else:
        lambdas = [float(x) for x in args.lambdas.split(",")]
        rows = collect_step_rows(args.dataset, args.episodes, lambdas, seed=args.seed, max_steps=args.max_steps,
                                 progress=not args.quiet)
        source = {"dataset": str(args.dataset), "episodes": args.episodes, "lambdas": lambdas, "seed": args.seed,
                  "max_steps": args.max_steps, "policy": "random (masked)"}
    source["command"] = " ".join(["perception-config fit-score", *(_argv_of(args))])
    frames = args.frames
    if frames is None and args.store is not None and (Path(args.store).parent / "frames").is_dir():
        frames = Path(args.store).parent / "frames"  # a configurator's learn_dir: its kept frames
    models = args.models if args.models is not None else (
        Path(args.dataset) / "models" if args.dataset is not None else None)
    table = featurise(rows, dataset=args.dataset if args.store is not None else None, progress=not args.quiet,
                      frames_dir=frames, models_dir=models)
    hidden = tuple(int(x) for x in args.hidden.split(",") if x.strip())
    base = None
    if args.recalibrate is not None:
        from ..blocks.pick_success import load_model

        base = load_model(str(args.recalibrate))
        source["recalibrated"] = str(args.recalibrate)
    metrics = fit_score(table, args.out, hidden=hidden, epochs=args.epochs, seed=args.seed, source=source, base=base)
    print(format_metrics(metrics))
    print(f"wrote {metrics['model']}, {metrics['reliability']} and {metrics['metrics_file']}")
    return 0


def _argv_of(args: argparse.Namespace) -> list[str]:
    """fit-score's options as given (recorded with the model, so it can be fitted again)."""
    out = ["--store", str(args.store)] if args.store is not None else []
    if args.dataset is not None:
        out += ["--dataset", str(args.dataset)]
    for flag, value in (("--frames", args.frames), ("--models", args.models)):
        if value is not None:
            out += [flag, str(value)]
    if args.store is None:
        out += ["--episodes", str(args.episodes), "--lambdas", args.lambdas, "--max-steps", str(args.max_steps)]
    if args.recalibrate is not None:
        out += ["--recalibrate", str(args.recalibrate)]
    return out + ["--hidden", args.hidden, "--epochs", str(args.epochs), "--seed", str(args.seed),
                  "--out", str(args.out)]


def _add_fit_score_parser(sub: Any) -> None:
    fs = sub.add_parser(
        "fit-score", help="fit the learned pick-success score (block pick_success) from stored or played episodes",
        description="Fit the pick_success model: features of every hypothesis of the episodes (the episode store's "
                    "step rows, or episodes played here with a random masked policy), labelled by the pick "
                    "criterion against the ground truth; a small MLP, Platt-calibrated on held-out images; "
                    "prints AUC, Brier and ECE on the held-out test images.")
    fs.add_argument("--store", type=Path, help="an episode store (SQLite) to learn from")
    fs.add_argument("--dataset", type=Path, help="a BOP dataset to play episodes on; with --store: the dataset "
                                                 "folder the store's rows refer to (default: the path they name)")
    fs.add_argument("--frames", type=Path, default=None,
                    help="with --store: the frames the configurator kept (learn_frames), for its estimates' rows "
                         "(default: frames/ beside the store, a learn_dir's); labelled by their ground truth, else "
                         "by the robot's reported pick outcomes")
    fs.add_argument("--models", type=Path, default=None,
                    help="the models folder of the kept frames' objects (default: the --dataset's models/)")
    fs.add_argument("--episodes", type=int, default=1500, help="episodes to play (--dataset)")
    fs.add_argument("--lambdas", default="0.1,0.3,0.5,0.7,1.0", help="noise levels of the played episodes")
    fs.add_argument("--max-steps", type=int, default=8, help="actions per played episode at most")
    fs.add_argument("--recalibrate", metavar="MODEL", default=None,
                    help="keep this model's network, fit only its calibration to these episodes (e.g. a real camera "
                         "or cell's); 'pick_success' is the shipped one")
    fs.add_argument("--hidden", default="32,16", help="hidden layer widths of the MLP")
    fs.add_argument("--epochs", type=int, default=300, help="full-batch Adam steps")
    fs.add_argument("--seed", type=int, default=0)
    fs.add_argument("--out", type=Path, required=True, help="folder for the model, reliability.png, metrics.json")
    fs.add_argument("--quiet", action="store_true", help="no progress bars")
    fs.set_defaults(func=_cmd_fit_score)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from ..learning.evaluation import DEFAULT_LAMBDAS, evaluate, format_table

    lambdas = [float(x) for x in args.lambdas.split(",")] if args.lambdas else list(DEFAULT_LAMBDAS)
    results = evaluate(
        args.dataset, args.policy, lambdas, args.out, episodes_per_lambda=args.episodes, seed=args.seed,
        pipeline=args.pipeline, split_seed=args.split_seed, test_fraction=args.test_fraction,
        include_baselines=not args.no_baselines, progress=not args.quiet, split=args.split, plots=not args.no_plots,
        time_mode=args.time_mode, max_ops=args.max_ops, use_depth=args.use_depth,
        store_episodes=args.store_episodes, workers=args.workers, ray_address=args.ray_address,
        oracle_budget=args.oracle_budget,
    )
    print(format_table(json.loads(results.read_text())))
    print(f"wrote {results} and the per-episode traces, BOP CSVs and plots in {results.parent}")
    print(f"BOP results for bop_toolkit, with the targets file of the evaluated episodes: {results.parent / 'bop'}")
    return 0


def _add_evaluate_parser(sub: argparse._SubParsersAction) -> None:
    ev = sub.add_parser("evaluate", help="compare agents on the test images over noise levels (Fig. 5)")
    _add_dataset_args(ev)
    ev.add_argument("--out", type=Path, required=True, help="output folder (results.json, plots, BOP CSVs)")
    ev.add_argument("--policy", action="append", default=[], metavar="FILE|AGENT",
                    help="a policy file or an agent name (random, simple, ...); repeatable")
    ev.add_argument("--lambdas", default=None, help="comma-separated noise levels (default 0.1,...,1.0)")
    ev.add_argument("--episodes", type=int, default=None, help="episodes per lambda (default: every test episode)")
    ev.add_argument("--seed", type=int, default=0, help="episode seeds (the same for every agent)")
    ev.add_argument("--pipeline", type=Path, default=None,
                    help="pipeline YAML or shipped name (default, rgb, cell, pick_success; default: the policy's, "
                         "else default)")
    ev.add_argument("--split-seed", type=int, default=None,
                    help="train/test split seed (default: the policy's, else 0)")
    ev.add_argument("--test-fraction", type=float, default=None,
                    help=f"test share of the images (default: the policy's, else {DEFAULT_TEST_FRACTION})")
    ev.add_argument("--time-mode", choices=TIME_MODES, default=None,
                    help="measured wall time or the blocks' cost table (default: the policy's, else measured)")
    ev.add_argument("--max-ops", type=int, default=None,
                    help=f"operations per episode (default: the policy's, else {EnvSettings().max_ops})")
    ev.add_argument("--split", default="test", help="BOP split folder of the dataset")
    ev.add_argument("--no-baselines", action="store_true", help="skip the oracle, fixed pipelines and random agent")
    ev.add_argument("--oracle-budget", type=int, default=None, metavar="N",
                    help="the oracle's operator calls per episode (default 2000; fewer where actions are "
                         "generator searches, e.g. the cell pipeline)")
    ev.add_argument("--no-plots", action="store_true")
    ev.add_argument("--no-episode-store", dest="store_episodes", action="store_false",
                    help="do not append the episodes to OUT/episodes.sqlite")
    _add_ray_args(ev, "the (agent, lambda) episodes")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.set_defaults(func=_cmd_evaluate)


def _add_ray_args(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help=f"play {what} as tasks on a local Ray with N worker processes (bound to 127.0.0.1, "
                             "no dashboard); default and 1: in this process, without Ray")
    parser.add_argument("--ray-address", default=None, metavar="ADDR",
                        help="join a running Ray cluster instead (e.g. 127.0.0.1:6379 of `ray start --head`, or "
                             "auto); the dataset path must exist on every node")


def _cmd_train(args: argparse.Namespace) -> int:
    from ..learning.training import train

    # Also when started with SIGINT ignored (a background job of a script inherits that): Ctrl-C
    # and `kill -INT` must stop the run with its work saved. SIGHUP ignored (nohup) stays ignored.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    lambda_range = tuple(args.lambda_range) if args.lambda_range else None
    settings = EnvSettings().replace(time_mode=args.time_mode, max_ops=args.max_ops, lambda_range=lambda_range)
    common = dict(
        settings=settings, pipeline=args.pipeline, progress=not args.quiet, resume=args.resume,
        test_fraction=args.test_fraction, split_seed=args.split_seed, workers=args.workers,
        ray_address=args.ray_address, overwrite=args.overwrite, checkpoint_every=args.checkpoint_every,
        use_depth=args.use_depth, store_episodes=args.store_episodes, validation_fraction=args.validation_fraction,
        validate_every=args.validate_every, agent_kwargs=agent_params(args.agent, args.agent_param),
    )
    if args.seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {args.seeds}")
    if args.seeds == 1:
        policy = train(args.dataset, args.agent, args.out, args.episodes, seed=args.seed, **common)
    else:
        from ..learning.seed_selection import SEEDS_CSV, train_seeds

        policy = train_seeds(args.dataset, args.agent, args.out, args.episodes,
                             list(range(args.seed, args.seed + args.seeds)), **common)
        print(Path(args.out, SEEDS_CSV).read_text(), end="")
    print(f"policy: {policy}")
    print(f"learning curve: {Path(args.out) / 'learning_curve.png'}")
    return 0


def agent_params(agent: str, items: list[str] | None) -> dict[str, Any]:
    """`--agent-param KEY=VALUE` options as the agent's hyper-parameters: VALUE read as JSON
    (numbers, lists, strings without quotes too), checked against the agent's bounds."""
    from ..agents import AGENTS
    from ..agents.hparams import check_hparams

    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--agent-param {item!r}: expected KEY=VALUE, e.g. entropy_coef=0.05")
        try:
            out[key.strip()] = json.loads(text)
        except json.JSONDecodeError:
            out[key.strip()] = text
    if out and agent in AGENTS:
        check_hparams(agent, AGENTS[agent].HPARAM_BOUNDS, out)
    return out


def _add_train_parser(sub: argparse._SubParsersAction) -> None:
    tr = sub.add_parser(
        "train", help="train a configuration agent on the train images of a BOP dataset",
        description="Ctrl-C (SIGINT), SIGTERM and SIGHUP stop the run: the round in flight is dropped, the workers "
                    "are stopped, and the policy, history.csv, learning curve and checkpoint of the last completed "
                    "round are written (a second signal does not abort that). Exit codes: 0 done, 2 bad input, "
                    "130 SIGINT, 143 SIGTERM, 129 SIGHUP; --resume continues the run.")
    _add_dataset_args(tr)
    tr.add_argument("--agent", choices=("random", "simple", "pg", "es", "fixed"), default="pg")
    tr.add_argument("--out", type=Path, required=True, help="run folder: policy, checkpoint, learning curve")
    tr.add_argument("--episodes", type=int, default=1000)
    env = EnvSettings()
    tr.add_argument("--lambda-range", type=float, nargs=2, default=None, metavar=("A", "B"),
                    help="lambda of the training episodes ~ U(A, B) "
                         f"(default {env.lambda_range[0]:g} {env.lambda_range[1]:g})")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--seeds", type=int, default=1, metavar="N",
                    help="train N runs (seeds --seed .. --seed+N-1, in OUT/seed-<s>/) and ship the one of lowest "
                         "validation cost as OUT/policy.safetensors, with OUT/seeds.csv; needs --validation-fraction "
                         "(default 1: one run in OUT)")
    tr.add_argument("--pipeline", type=Path, default=None,
                    help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                         "(default: default)")
    tr.add_argument("--time-mode", choices=TIME_MODES, default=None, help=f"(default {env.time_mode})")
    tr.add_argument("--max-ops", type=int, default=None, help=f"operations per episode (default {env.max_ops})")
    tr.add_argument("--test-fraction", type=float, default=DEFAULT_TEST_FRACTION,
                    help="share of image ids held out for evaluation")
    tr.add_argument("--split-seed", type=int, default=DEFAULT_SPLIT_SEED)
    tr.add_argument("--checkpoint-every", type=int, default=100, metavar="N",
                    help="write the checkpoint every N episodes (100); a stop signal always writes it")
    tr.add_argument("--validation-fraction", type=float, default=0.0, metavar="F",
                    help="hold out this share of the train images (seeded by --split-seed; the test images are "
                         "untouched), check the greedy policy on them every --validate-every episodes and at the "
                         "end, and ship the one with the lowest mean cost (0: the last policy; default 0)")
    tr.add_argument("--validate-every", type=int, default=DEFAULT_VALIDATE_EVERY, metavar="K",
                    help=f"episodes between two validation checks ({DEFAULT_VALIDATE_EVERY})")
    tr.add_argument("--agent-param", action="append", metavar="KEY=VALUE",
                    help="an agent hyper-parameter (repeatable), e.g. pg's entropy_coef=0.05 lr_half_life=2000 "
                         "(checked against the agent's bounds; ignored by --resume, which keeps the checkpoint's)")
    tr.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    tr.add_argument("--overwrite", action="store_true", help="start again over an existing run in --out")
    tr.add_argument("--no-episode-store", dest="store_episodes", action="store_false",
                    help="do not append the episodes to OUT/episodes.sqlite")
    _add_ray_args(tr, "each round's episodes (pg's batch, the ES population; a round waits for its slowest "
                      "episode, so give pg batch_episodes >= 4 N)")
    tr.add_argument("--quiet", action="store_true")
    tr.set_defaults(func=_cmd_train)


def _cmd_launch(args: argparse.Namespace) -> int:
    from ..launcher.launch import parse_nodes, resolve_nodes, run

    specs = resolve_nodes(
        parse_nodes(args.nodes) if args.nodes else None, models=args.models, pipeline=args.pipeline,
        policy=args.policy, bag=args.bag, rate=args.rate, params_file=args.params_file,
        say=lambda text: print(f"[launch] {text}", flush=True), remaps=_remaps(args.remap or []),
    )
    return run(specs, log_dir=args.log_dir)


def _remaps(items: list[str]) -> dict[str, str]:
    """--remap FROM:=TO options as a mapping; a malformed one is a clear error."""
    out = {}
    for item in items:
        source, sep, target = item.partition(":=")
        if not sep or not source or not target:
            raise ValueError(f"--remap {item!r}: expected FROM:=TO, e.g. "
                             "camera/color/image_raw:=/camera/camera/color/image_raw")
        out[source] = target
    return out


def _add_launch_parser(sub: argparse._SubParsersAction) -> None:
    la = sub.add_parser(
        "launch", help="start the ROS 2 nodes as processes, stream their logs, stop them on Ctrl-C",
        description="Start the nodes as separate processes with the loopback ROS defaults; their output is "
                    "printed as [node_name] lines. Ctrl-C or SIGTERM stops them all (SIGINT, then SIGKILL after "
                    "10 s; exit 0 if all stopped cleanly). A node that dies stops the others (exit 1).",
    )
    la.add_argument("--nodes", default=None, metavar="LIST",
                    help="comma-separated, from: generation, refinement, scoring, pick, configurator, bag_replay "
                         "(default: generation,refinement,scoring,pick,configurator)")
    la.add_argument("--models", type=Path, default=None, metavar="DIR",
                    help="BOP models folder "
                         "(default: data/default/models, else the procedural parts in data/parts_models)")
    la.add_argument("--pipeline", type=Path, default=None, metavar="YAML|NAME",
                    help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                         "(default: default; cell = the real-camera set-up without ground truth, README "
                         "'A real robot cell')")
    la.add_argument("--policy", default=None, metavar="FILE|none",
                    help="configurator policy "
                         "(default: the newest runs/*/policy.safetensors; none = the fixed pipeline)")
    la.add_argument("--bag", type=Path, default=None, metavar="FILE",
                    help="also start bag_replay_node on this MCAP bag")
    la.add_argument("--rate", type=float, default=None, metavar="R", help="bag_replay_node's replay rate")
    la.add_argument("--params-file", type=Path, default=None, metavar="YAML",
                    help="ROS params file passed to every node; the options above win over it")
    la.add_argument("--remap", action="append", metavar="FROM:=TO",
                    help="topic remapping for the operator nodes and the configurator (repeatable), e.g. the "
                         "camera driver's topics: camera/color/image_raw:=/camera/camera/color/image_raw")
    la.add_argument("--log-dir", type=Path, default=None, metavar="DIR",
                    help="also write each node's output to DIR/<node>.log")
    la.set_defaults(func=_cmd_launch)


def _cmd_replay_check(args: argparse.Namespace) -> int:
    from ..ros import replay_check  # imports rclpy: only for this command

    return replay_check.run_cli(args)


def _add_replay_check_parser(sub: argparse._SubParsersAction) -> None:
    rc = sub.add_parser(
        "replay-check", help="record test images to MCAP, replay them through the nodes, compare with in-process",
        description="Record the policy's test images to MCAP, replay them through generation/refinement/scoring/pick/"
                    "configurator/bag_replay nodes (separate processes), estimate every object with estimate_pose and "
                    "compare success and operator time with the same episodes in-process. Exit 0 when the success "
                    "rates agree within binomial noise.",
    )
    rc.add_argument("--dataset", required=True, help="BOP dataset folder (its test split is replayed)")
    rc.add_argument("--policy", default=None, help="policy file (default: the fixed pipeline)")
    rc.add_argument("--pipeline", default=None, help="pipeline YAML (default: the policy's, else the built-in one)")
    rc.add_argument("--out", default="outputs/replay_check", help="folder for the bag, logs, results.json and the plot")
    rc.add_argument("--images", type=int, default=8, help="test images to record and replay (8)")
    rc.add_argument("--lambda", dest="noise_lambda", type=float, default=0.5, help="noise level of the episodes (0.5)")
    rc.add_argument("--rate", type=float, default=1.0, help="replay rate, x the recorded 10 Hz (1.0)")
    rc.set_defaults(func=_cmd_replay_check)


def _cmd_cell_sim(args: argparse.Namespace) -> int:
    from ..ros import cell_sim_run  # imports rclpy: only for this command

    return cell_sim_run.run_cli(args)


def _add_cell_sim_parser(sub: argparse._SubParsersAction) -> None:
    cs = sub.add_parser(
        "cell-sim", help="a simulated robot cell: a bag replayed in a loop through the nodes, every object estimated "
                         "and picked (simulated) while the configurator learns; plotted against a reference policy",
        description="Replay a bag in a loop through the operator nodes and the configurator (separate processes, "
                    "loopback), estimate every object of each frame the cell sees with estimate_pose, one after "
                    "the other, while the configurator learns (learn:=true; --no-learn: it serves the start as "
                    "it is). The reference policy is run through the same nodes for one round first. Writes "
                    "OUT/estimates.csv (per estimate), OUT/reference.csv, OUT/cell_sim.png, OUT/summary.json and "
                    "prints when the rolling window came within the tolerance of the reference and every "
                    "promotion's replay-check cost against its predecessor. Ctrl-C keeps what ran (exit 130).",
    )
    source = cs.add_mutually_exclusive_group(required=True)
    source.add_argument("--bag", type=Path, help="a bag with ground truth (perception-config bag write)")
    source.add_argument("--dataset", type=Path,
                        help="BOP dataset: its test images (the reference policy's split) go to OUT/cell.mcap")
    cs.add_argument("--models", type=Path, default=None,
                    help="BOP models folder with --bag (default: data/default/models); --dataset brings its own")
    cs.add_argument("--images", type=int, default=None, help="with --dataset: record only the first N test images")
    cs.add_argument("--start", default="fixed", metavar="fixed|untrained|POLICY",
                    help="what serves first: the fixed sequence, an untrained pg policy (learning only) or a policy "
                         "file (default fixed)")
    cs.add_argument("--fixed-sequence", default=None, metavar="A,B,...",
                    help="the fixed sequence of --start fixed (default: the configurator's, icp_coarse,icp_fine,pick; "
                         "the best on the demo dataset is d2co,icp_fine,pick)")
    cs.add_argument("--reference", type=Path, required=True, metavar="POLICY",
                    help="the offline-trained policy whose success and time are the reference lines")
    cs.add_argument("--reference-from", type=Path, default=None, metavar="CSV",
                    help="reuse a previous run's reference.csv instead of measuring the reference again")
    cs.add_argument("--reference-rounds", type=int, default=1, metavar="R",
                    help="rounds over the bag (every object of every frame once each) for the reference (1)")
    cs.add_argument("--estimates", type=int, default=200, help="estimates of the cell (200)")
    cs.add_argument("--out", type=Path, required=True, help="output folder")
    cs.add_argument("--no-learn", dest="learn", action="store_false",
                    help="serve the start without learning (a baseline; the configurator gets no learn parameters)")
    cs.add_argument("--learn-every", type=int, default=None, metavar="K",
                    help="new estimates between two candidate trainings (the configurator's learn_every)")
    cs.add_argument("--learn-margin", type=float, default=None, metavar="M",
                    help="a candidate is promoted if its replay-check cost is lower by this fraction (learn_margin)")
    cs.add_argument("--lambda", dest="noise_lambda", type=float, default=0.5,
                    help="noise level of the simulated initial hypotheses (0.5)")
    cs.add_argument("--seed", type=int, default=0, help="the estimates' seeds")
    cs.add_argument("--rate", type=float, default=1.0, help="replay rate, x the recorded timing (1.0)")
    cs.add_argument("--window", type=int, default=200, help="estimates in the rolling window (200)")
    cs.add_argument("--quiet", action="store_true", help="no progress bar")
    cs.set_defaults(func=_cmd_cell_sim)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="perception-config", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="write a synthetic BOP-format dataset")
    s.add_argument("--out", type=Path, required=True, help="output dataset folder")
    s.add_argument("--scenes", type=int, default=4)
    s.add_argument("--images-per-scene", type=int, default=10)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--models", type=Path, default=None,
                   help="a BOP models/ folder to place instead of the procedural parts")
    s.add_argument("--no-depth", dest="depth", action="store_false",
                   help="write an RGB-only dataset (no depth folders; the same images and annotations)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synth)

    b = sub.add_parser("bag", help="record BOP scenes to MCAP and inspect rosbag2 bags (MCAP or sqlite3)")
    bsub = b.add_subparsers(dest="bag_command", required=True)
    bw = bsub.add_parser("write", help="record a BOP dataset as a rosbag2-compatible MCAP file")
    _add_dataset_args(bw)
    bw.add_argument("--out", type=Path, required=True)
    bw.add_argument("--split", default="test")
    bw.add_argument("--rate", type=float, default=10.0, help="frames per second on the recording's clock")
    bw.add_argument("--quiet", action="store_true")
    bw.set_defaults(func=_cmd_bag_write)
    bi = bsub.add_parser("info", help="summarise a bag: topics, types, counts, compression, and the colour, depth "
                         "and camera_info topics it would read (or the candidates when it cannot choose)")
    bi.add_argument("file", type=Path, help=".mcap or .db3 file, or a rosbag2 bag directory")
    bi.add_argument("--json", action="store_true", help="print the summary as JSON")
    bi.set_defaults(func=_cmd_bag_info)

    sh = sub.add_parser("show", help="write a PNG of a frame with the ground-truth models overlaid")
    _add_dataset_args(sh)
    sh.add_argument("--out", type=Path, required=True)
    sh.add_argument("--scene", type=int, default=None, help="scene id (default: the first)")
    sh.add_argument("--image", type=int, default=None, help="image id (default: the first)")
    sh.add_argument("--split", default="test")
    sh.set_defaults(func=_cmd_show)
    bl = sub.add_parser("blocks", help="list the building blocks with their parameters")
    bl.set_defaults(func=_cmd_blocks)

    be = sub.add_parser("bench", help="benchmarks of the building blocks (one core)")
    besub = be.add_subparsers(dest="bench_command", required=True)
    for name, func, helptext in (
        ("blocks", _cmd_bench_blocks, "median/p90 ms per call of every block"),
        ("convergence", _cmd_bench_convergence, "share of successful picks per refiner and lambda"),
    ):
        c = besub.add_parser(name, help=helptext)
        _add_dataset_args(c)
        c.add_argument("--out", type=Path, required=True, help="JSON output file")
        c.add_argument("--pipeline", type=Path, default=None,
                       help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                            "(default: default)")
        c.add_argument("--frames", type=int, default=10, help="number of images to use")
        c.add_argument("--split", default="test")
        c.add_argument("--quiet", action="store_true")
        c.set_defaults(func=func)
        if name == "blocks":
            c.add_argument("--noise-lambda", type=float, default=0.2, help="noise of the benchmarked hypotheses")
        else:
            c.add_argument("--lambdas", default="0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0")
            c.add_argument("--applications", type=int, default=5, help="max applications of the refiner")
    c = besub.add_parser("real", help="refiners and scores on a BOP dataset's frames (with or without depth)")
    _add_dataset_args(c)
    c.add_argument("--out", type=Path, required=True, help="folder for real.json and real.png, or a .json file")
    c.add_argument("--pipeline", type=Path, default=None,
                   help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                        "(default: default)")
    c.add_argument("--frames", type=int, default=None, help="number of images to use (default: all)")
    c.add_argument("--seeds", type=int, default=5, help="perturbations per object and lambda")
    c.add_argument("--lambdas", default="0,0.1,0.3", help="starting noise levels of the refiners (0 = ground truth)")
    c.add_argument("--calls", type=int, default=3, help="successive calls of a refiner")
    c.add_argument("--min-visib", type=float, default=0.3, help="smallest visib_fract of an object")
    c.add_argument("--blocks", default=None, help="comma-separated action / block names (default: all)")
    c.add_argument("--no-refiner-costs", action="store_true", help="do not rank the refiners' own costs as scores")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--split", default="test")
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=_cmd_bench_real)
    _add_train_parser(sub)
    _add_evaluate_parser(sub)
    _add_launch_parser(sub)
    ep = sub.add_parser("episodes", help="the episode store (episodes.sqlite of a run): summary and export")
    epsub = ep.add_subparsers(dest="episodes_command", required=True)
    ei = epsub.add_parser("info", help="schema version, size, episodes per source/agent and per object with the "
                          "success share and mean time")
    ei.add_argument("store", type=Path, help="an episodes.sqlite file")
    ei.add_argument("--json", action="store_true", help="print the summary as JSON")
    ei.set_defaults(func=_cmd_episodes_info)
    ee = epsub.add_parser("export", help="write a table of the store as CSV or Parquet (by --out's suffix)")
    ee.add_argument("store", type=Path, help="an episodes.sqlite file")
    ee.add_argument("--out", type=Path, required=True, help="FILE.csv or FILE.parquet (written atomically)")
    ee.add_argument("--table", choices=("episodes", "steps", "pick_outcomes"), default="episodes")
    ee.set_defaults(func=_cmd_episodes_export)

    _add_replay_check_parser(sub)
    _add_cell_sim_parser(sub)
    _add_fit_score_parser(sub)
    return p


def _show_data_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """Warnings about the user's data (a repaired annotation) as one line naming the file; other
    warnings keep Python's format (they are for developers)."""
    if issubclass(category, UserWarning) and category.__module__.startswith("perception_config"):
        print(f"warning: {message}", file=sys.stderr if file is None else file)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)


_python_showwarning = warnings.showwarning


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    warnings.showwarning = _show_data_warning
    try:
        return int(args.func(args) or 0)
    except (FileNotFoundError, FileExistsError, ValueError, KeyError) as exc:
        # Bad input: one clear line naming what was wrong, no traceback.
        print(f"perception-config {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        # A job stopped by a signal (StopRequested names it, e.g. train; otherwise 130): exit 128 +
        # the signal number, the shell's convention (130 SIGINT, 143 SIGTERM, 129 SIGHUP). One more
        # Ctrl-C while the StopRequested was on its way here raises over it: it still names the stop.
        _ignore_further_signals()
        cause: BaseException | None = exc
        while cause is not None and not isinstance(cause, StopRequested):
            cause = cause.__context__
        exc = cause if cause is not None else exc
        code = exc.exit_code if isinstance(exc, StopRequested) else 130
        _say_quietly(f"perception-config {args.command}: {str(exc) or 'interrupted'}")
        return code


def _ignore_further_signals() -> None:
    """The work is saved and the process is leaving: a further stop signal (one more Ctrl-C)
    must not turn the exit code into death by SIGINT. Ignored ones stay ignored through the
    interpreter's shutdown (handlers set in Python are reset to the default there)."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)


def _say_quietly(text: str) -> None:
    """A last line on stderr; after SIGHUP the terminal may be gone: then stdout and stderr go
    to /dev/null, so flushing them at exit cannot turn the exit code into 120."""
    try:
        print(text, file=sys.stderr, flush=True)
        sys.stdout.flush()
    except OSError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.dup2(devnull, sys.stderr.fileno())


if __name__ == "__main__":
    sys.exit(main())
