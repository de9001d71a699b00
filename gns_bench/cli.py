"""gns-bench: reproduce and benchmark the Graph Network-based Simulator of "Learning to Simulate Complex Physics
with Graph Networks" (Sanchez-Gonzalez et al., ICML 2020). Generate particle datasets with real solvers, train
and evaluate the GNS on them with every MLflow-tracked detail, run the paper's experiments as sweeps, and
compile reports with the paper's numbers beside ours. Start with `gns-bench quickstart`.

(The module itself is a thin command line over the library: it parses, calls and prints.)"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from pathlib import Path

from gns_bench.config import TIERS, ConfigError
from gns_bench.data.format import DatasetError

CONFIGS = Path(__file__).resolve().parent / "configs"
DATASET_HELP = "dataset directory (metadata.json and train/valid/test.h5), e.g. data/goop-small-s0"


def _add_generate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("generate", help="generate a dataset for a domain (the 16 paper domains, their variants, "
                                        "or 'tiny')")
    p.add_argument("domain", help="domain id (e.g. waterdrop, sand-3d, boxbath, or tiny: no physics engine) or a "
                                  "variant in datasets/variants/ (e.g. waterramps-inflow); 'list' prints them all")
    p.add_argument("--tier", default="smoke", choices=TIERS,
                   help="smoke: seconds (tests); small: ~10-25 min on 2 cores; cpu: at most 15 min on 2 cores (the "
                        "CPU campaign's); paper: the paper's sizes")
    p.add_argument("--seed", type=int, default=0, help="dataset seed: the same seed gives the same files")
    p.add_argument("--out", type=Path, default=None, help="dataset directory (default data/<domain>-<tier>-s<seed>)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    p.add_argument("--time", type=float, default=None, metavar="SECONDS",
                   help="write nothing: simulate the tier's first training trajectories for about SECONDS and "
                        "estimate how long the whole dataset takes on this machine")


def cmd_generate(args: argparse.Namespace) -> None:
    import shutil

    from gns_bench.datasets import check_domain, dataset_path, ensure_dataset

    if args.domain == "list":
        from gns_bench.datasets import list_domains, list_variants

        print("domains:  " + " ".join(list_domains()))
        print("variants: " + " ".join(list_variants()))
        return
    if args.time is not None:
        from gns_bench.devices import cpu_model
        from gns_bench.physics.generate import time_generation

        check_domain(args.domain)
        if args.domain == "tiny":
            raise SystemExit("gns-bench generate: 'tiny' is made by numpy in about a second; nothing to time")
        t = time_generation(args.domain, args.tier, args.time, args.seed)
        print(f"{t.domain} tier {t.tier}: {t.seconds_per_trajectory:.2f} s a trajectory ({t.timed} timed, "
              f"{t.mean_particles:.0f} particles on average; the first, compiling included, {t.first_seconds:.1f} s) "
              f"on {cpu_model()}: its {t.trajectories} trajectories in about {t.estimated_minutes:.1f} min")
        return
    out = args.out or dataset_path(args.domain, args.tier, args.seed)
    if args.overwrite and out.exists():
        check_domain(args.domain)  # refuse an unknown domain before deleting anything
        shutil.rmtree(out)
    path = ensure_dataset(args.domain, args.tier, args.seed, out=out)
    print(path)


def _add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="draw a trajectory of a dataset as a PNG strip and a GIF")
    p.add_argument("dataset", type=Path, help=DATASET_HELP)
    p.add_argument("--split", default="test", choices=["train", "valid", "test"], help="which split")
    p.add_argument("--traj", type=int, default=0, help="trajectory index within the split")
    p.add_argument("--out", type=Path, default=None, help="output path stem (default beside the dataset)")


def cmd_render(args: argparse.Namespace) -> None:
    from gns_bench.physics.render import render_dataset

    png, gif = render_dataset(args.dataset, args.split, args.traj, args.out)
    print(png)
    print(gif)


def _add_import(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import", help="convert another project's dataset layout into ours")
    p.add_argument("source_format", choices=["deepmind", "npz"],
                   help="deepmind: the original TFRecord release; npz: geoelements/gns")
    p.add_argument("src", type=Path, help="source directory (metadata.json + train/valid/test files)")
    p.add_argument("dst", type=Path, help="new dataset directory")
    p.add_argument("--overwrite", action="store_true", help="replace dst if it exists")


def cmd_import(args: argparse.Namespace) -> None:
    from gns_bench.data.importers import import_deepmind, import_npz

    importer = import_deepmind if args.source_format == "deepmind" else import_npz
    print(importer(args.src, args.dst, overwrite=args.overwrite))


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a GNS on a dataset, tracked in MLflow",
                       description="Overrides are section.key=value, e.g. model.message_passing_steps=5 "
                                   "train.steps=1000 train.noise_std=6.7e-4")
    p.add_argument("dataset", type=Path, help=DATASET_HELP)
    p.add_argument("overrides", nargs="*", help="section.key=value overrides of the config")
    p.add_argument("--config", type=Path, default=None, help="TOML config (default: the paper's defaults)")
    p.add_argument("--out", type=Path, default=None, help="run directory (default runs/<dataset>)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint in --out")
    p.add_argument("--experiment", default="gns-bench", help="MLflow experiment name")
    p.add_argument("--no-eval", action="store_true", help="skip the evaluation after training")


def cmd_train(args: argparse.Namespace) -> None:
    from gns_bench.config import load_config
    from gns_bench.pipeline import train_run

    config = load_config(args.config, args.overrides)
    out = args.out or Path("runs") / args.dataset.name
    summary = train_run(config, args.dataset, out, experiment=args.experiment, resume=args.resume,
                        evaluate_after=not args.no_eval)
    _print_summary(summary)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="one-step and rollout MSE of a checkpoint on a split, tracked in MLflow")
    p.add_argument("checkpoint", type=Path, help="checkpoint file or run directory")
    p.add_argument("dataset", type=Path, help=DATASET_HELP)
    p.add_argument("--split", default=None, choices=["valid", "test"], help="default: test")
    p.add_argument("--max-trajectories", type=int, default=None, help="evaluate the first N trajectories")
    p.add_argument("--rollout-steps", type=int, default=None, help="cut rollouts at K steps (default: whole)")
    p.add_argument("--out", type=Path, default=None, help="where rollouts and pictures go "
                   "(default: <run directory>/evaluation)")
    p.add_argument("--experiment", default="gns-bench", help="MLflow experiment name")
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu, cuda, cuda:1, ...")
    p.add_argument("--into", metavar="RUN_ID", default=None,
                   help="evaluate the run directory's final checkpoint again into the MLflow run that trained it, "
                        "with that run's evaluation settings (changed only by the options given), as "
                        "`sweep --reevaluate` does for the runs a sweep plans")
    p.add_argument("--reason", default="gns-bench evaluate --into", help="with --into: tag 'reevaluated' says why")


def cmd_evaluate(args: argparse.Namespace) -> None:
    from gns_bench.config import EvalConfig
    from gns_bench.pipeline import evaluate_run, reevaluate_run, trained_eval_config

    changes = {name: value for name, value in (("split", args.split), ("max_trajectories", args.max_trajectories),
                                               ("rollout_steps", args.rollout_steps)) if value is not None}
    if args.into:
        eval_config = trained_eval_config(args.checkpoint, **changes)
        _print_summary(reevaluate_run(args.into, args.dataset, args.checkpoint, eval_config, reason=args.reason,
                                      device=args.device))
        return
    eval_config = EvalConfig(**{"split": "test", **changes})
    eval_config.validate()
    _print_summary(evaluate_run(args.checkpoint, args.dataset, eval_config, out_dir=args.out,
                                experiment=args.experiment, device=args.device))


def _add_rollout(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rollout", help="roll a checkpoint out on one trajectory; save it with a picture")
    p.add_argument("checkpoint", type=Path, help="checkpoint file or run directory")
    p.add_argument("dataset", type=Path, help=DATASET_HELP)
    p.add_argument("--split", default="test", choices=["train", "valid", "test"], help="which split")
    p.add_argument("--traj", type=int, default=0, help="trajectory index within the split")
    p.add_argument("--steps", type=int, default=None, help="rollout length (default: to the end)")
    p.add_argument("--out", type=Path, default=None, help="output stem (default rollout-<split>-<traj>)")
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu, cuda, cuda:1, ...")


def cmd_rollout(args: argparse.Namespace) -> None:
    from gns_bench.pipeline import save_rollout

    saved = save_rollout(args.checkpoint, args.dataset, args.split, args.traj, args.steps, args.out, args.device)
    print(f"rollout MSE {saved.errors['rollout_mse']:.4g} (the paper's definition; moving particles only: "
          f"{saved.errors['rollout_mse_moving']:.4g}) over {saved.steps} steps")
    print(f"{saved.npz}\n{saved.png}")


def _add_sweep(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="run every run of a sweep spec (sweeps/**/*.toml), tracked in MLflow")
    p.add_argument("file", type=Path, help="sweep TOML, e.g. sweeps/ablations/noise_std.toml")
    p.add_argument("--tier", default="smoke", choices=TIERS,
                   help="budget (sweeps/tiers.toml): smoke, seconds a run (a pipeline check); small, hours a run on 2 "
                        "CPU cores; cpu, the campaign's budget, at most 30 minutes a run on 2 cores; "
                        "paper, the paper's 20M steps")
    p.add_argument("--dry-run", action="store_true", help="print the table of runs and their status; run nothing")
    p.add_argument("--time", action="store_true",
                   help="like --dry-run, and measure each run's training steps a second here on its own data (a few "
                        "steps of its own loop), with the training time its steps would take and the total still "
                        "to train: how a tier's steps are chosen")
    p.add_argument("--launcher", default="local", choices=["local", "submitit"],
                   help="local: one run after another here; submitit: a job array (SLURM, else local processes)")
    p.add_argument("--parallel", type=int, default=1, metavar="N",
                   help="local launcher: N runs at once, each in its own process on its own share of the cores "
                        "(on a GPU they share the device), its progress in progress.log in its run directory; "
                        "default 1")
    p.add_argument("--cluster", default=None, choices=["local", "slurm", "debug"],
                   help="submitit executor (default: SLURM when available, else local)")
    p.add_argument("--no-share", action="store_true",
                   help="train every run here, even one another sweep already trained with the same config and "
                        "data (by default it is recorded from that run: an ablation's default point is the "
                        "domain sweep's run)")
    p.add_argument("--only", action="append", default=[], metavar="PATTERN",
                   help="run only the runs whose names match this shell pattern (repeatable), e.g. "
                        "'message_passing_steps=5-*'; --dry-run lists the names")
    p.add_argument("--no-train", action="store_true",
                   help="train nothing: only record the runs other sweeps already trained (shared)")
    p.add_argument("--any-cpu-kind", action="store_true",
                   help="train here the runs held to another kind of machine (by default an ablation's or a "
                        "study's runs train on the CPU kind most of them trained on, and a started run resumes on "
                        "the kind it began on, so that compared runs share one kind: gns_bench/sweep/cpu_kinds.py)")
    p.add_argument("--reevaluate", nargs="?", const="the evaluation changed", default=None, metavar="REASON",
                   help="first evaluate the finished runs again from their final checkpoints, into their own MLflow "
                        "runs (tag 'reevaluated' records REASON), and copy shared runs afresh; then the sweep runs "
                        "what it lacks as usual (add --no-train to train nothing)")
    p.add_argument("--data-root", type=Path, default=Path("data"), help="where datasets are found or made")
    p.add_argument("--runs-root", type=Path, default=Path("runs"), help="where run directories go")
    p.add_argument("--reports-root", type=Path, default=Path("reports"),
                   help="where the committed run summaries (<sweep>/<tier>/runs.json) are read: a run one holds is "
                        "finished even when this MLflow store lacks it")


def cmd_sweep(args: argparse.Namespace) -> None:
    from gns_bench.sweep.runner import format_plan, prepare, run_sweep
    from gns_bench.sweep.spec import load_sweep

    sweep = load_sweep(args.file)
    if args.time:
        from gns_bench.sweep.timing import timed_plan

        timed_plan(sweep, args.tier, args.data_root, share=not args.no_share, only=args.only,
                   reports_root=args.reports_root)
        return
    if args.dry_run:
        runs, status, _ = prepare(sweep, args.tier, args.data_root, generate=False, share=not args.no_share,
                                  only=args.only, reports_root=args.reports_root, any_kind=args.any_cpu_kind,
                                  runs_root=args.runs_root)
        print(format_plan(sweep, args.tier, runs, status))
        return
    outcomes = run_sweep(sweep, args.tier, data_root=args.data_root, runs_root=args.runs_root,
                         launcher=args.launcher, cluster=args.cluster, share=not args.no_share, only=args.only,
                         train=not args.no_train, reevaluate_reason=args.reevaluate, parallel=args.parallel,
                         reports_root=args.reports_root, any_kind=args.any_cpu_kind)
    counts = {s: sum(o.status == s for o in outcomes)
              for s in ("FINISHED", "REEVALUATED", "SKIPPED", "SHARED", "FAILED", "WAITING")}
    print(f"sweep {sweep.name}: {counts['FINISHED']} finished, "
          + (f"{counts['REEVALUATED']} evaluated again, " if args.reevaluate is not None else "")
          + f"{counts['SKIPPED']} skipped (already finished), "
          f"{counts['SHARED']} shared (trained by another sweep), {counts['FAILED']} failed"
          + (f", {counts['WAITING']} waiting (listed above)" if counts["WAITING"] else "")
          + f"; MLflow experiment '{sweep.experiment}'")
    for outcome in outcomes:
        if outcome.status == "FAILED":
            print(f"  FAILED {outcome.name}: {outcome.error}")
    if counts["FAILED"]:
        raise SystemExit(1)


def _add_campaign(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("campaign", help="run a campaign's sweeps in priority order (resumable), then write every "
                                        "report", description="A campaign file (sweeps/campaigns/*.toml) lists "
                                        "sweeps in order; each runs what it lacks, its report is written when it "
                                        "is done, and every report at the end. Rerun the same command to resume.")
    p.add_argument("file", type=Path, help="campaign TOML, e.g. sweeps/campaigns/paper.toml")
    p.add_argument("--tier", default="smoke", choices=TIERS, help="the tier to run every sweep at")
    p.add_argument("--dry-run", action="store_true", help="print every sweep's runs and their status; run nothing")
    p.add_argument("--time", action="store_true",
                   help="like --dry-run, and measure every run's training steps a second here on its own data, with "
                        "the training time each run's steps would take and the campaign's total still to train")
    p.add_argument("--launcher", default="local", choices=["local", "submitit"],
                   help="local: one run after another here; submitit: job arrays (SLURM, else local processes)")
    p.add_argument("--parallel", type=int, default=1, metavar="N",
                   help="local launcher: N lanes, each a process on its own share of the cores (on a GPU they "
                        "share the device), kept busy across sweeps: a free lane takes the next run in the "
                        "campaign's order or makes the next sweep's datasets; each run's progress goes to "
                        "progress.log in its run directory; default 1")
    p.add_argument("--cluster", default=None, choices=["local", "slurm", "debug"], help="submitit executor")
    p.add_argument("--any-cpu-kind", action="store_true",
                   help="train here the runs held to another kind of machine (by default an ablation's or a "
                        "study's runs train on the CPU kind most of them trained on, and a started run resumes on "
                        "the kind it began on, so that compared runs share one kind: gns_bench/sweep/cpu_kinds.py)")
    p.add_argument("--data-root", type=Path, default=Path("data"), help="where datasets are found or made")
    p.add_argument("--runs-root", type=Path, default=Path("runs"), help="where run directories go")
    p.add_argument("--reports-root", type=Path, default=Path("reports"), help="where reports go")


def cmd_campaign(args: argparse.Namespace) -> None:
    from gns_bench.campaign import plan_campaign, run_campaign
    from gns_bench.sweep.campaigns import load_campaign

    campaign = load_campaign(args.file)
    if args.dry_run or args.time:
        plan_campaign(campaign, args.tier, args.data_root, timed=args.time, reports_root=args.reports_root,
                      runs_root=args.runs_root, any_kind=args.any_cpu_kind)
        return
    results = run_campaign(campaign, args.tier, data_root=args.data_root, runs_root=args.runs_root,
                           reports_root=args.reports_root, launcher=args.launcher, cluster=args.cluster,
                           parallel=args.parallel, any_kind=args.any_cpu_kind)
    failed = [(r.sweep, o) for r in results for o in r.outcomes if o.status == "FAILED"]
    broken = [r for r in results if r.error]
    done = sum(o.status in ("FINISHED", "SKIPPED", "SHARED", "REEVALUATED") for r in results for o in r.outcomes)
    waiting = sum(o.status == "WAITING" for r in results for o in r.outcomes)
    print(f"campaign {campaign.name} ({args.tier}): {len(results)} sweeps, {done} runs done, {len(failed)} failed, "
          f"{len(broken)} sweeps that could not run"
          + (f", {waiting} runs waiting (for another kind of machine, or for the checkpoint a branch starts "
             "from)" if waiting else ""))
    for sweep, outcome in failed:
        print(f"  FAILED {sweep}/{outcome.name}: {outcome.error}")
    for result in broken:
        print(f"  sweep {result.sweep}: {result.error}")
    if failed or broken:
        raise SystemExit(1)


def _add_report(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="compile a sweep's MLflow runs into reports/<sweep>/<tier>/ (markdown, PNG)")
    p.add_argument("sweep", help="sweep file or name (e.g. sweeps/ablations/noise_std.toml, ablation-noise_std), "
                                 "'domains' for the table across all domain sweeps, 'stability' for the "
                                 "stress sweeps, 'baselines' for GNS against CConv and DPI-Net, 'index' for the front "
                                 "page (reports/README.md: every claim of the paper), or 'all': every sweep with "
                                 "runs at the tier, then those four")
    p.add_argument("--tier", default="smoke", choices=TIERS, help="which tier's runs to compile")
    p.add_argument("--reports-root", type=Path, default=Path("reports"), help="where reports go")
    p.add_argument("--measure-cost", action="store_true",
                   help="baselines only: first time every comparison's models here, one after another (a few "
                        "training steps each on the tier's data, and their rollout steps), and keep the table in "
                        "the report: cost like for like on one machine (minutes; pause other jobs first)")
    p.add_argument("--data-root", type=Path, default=Path("data"), help="with --measure-cost: where the datasets are")


def cmd_report(args: argparse.Namespace) -> None:
    from gns_bench.report import write_all_reports, write_report

    if args.measure_cost:
        from gns_bench.bench.costs import measure_costs
        from gns_bench.report.baselines import write_baselines_report

        if args.sweep != "baselines":
            raise SystemExit(f"gns-bench report: --measure-cost times the baselines report's models; got sweep "
                             f"{args.sweep!r}, expected 'baselines'")
        measured = measure_costs(args.tier, args.data_root)
        print(write_baselines_report(args.tier, args.reports_root / "baselines" / args.tier, args.reports_root,
                                     measured=measured))
        return
    if args.sweep == "all":
        print("\n".join(map(str, write_all_reports(args.tier, args.reports_root))))
    else:
        print(write_report(args.sweep, args.tier, args.reports_root))


def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmark training and rollout speed against this machine's limits")
    p.add_argument("--out", type=Path, default=None,
                   help="where bench.json, README.md, PNG go (default: reports/bench/<machine>/, e.g. "
                        "amd-epyc-family-26-model-2-avx512bf16: the CPU's model, generation and bf16 unit; "
                        "reports/bench/README.md then compares every machine measured)")
    p.add_argument("--quick", action="store_true", help="small sizes: seconds, for a first look")
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu, cuda, cuda:1, ...")
    p.add_argument("--no-mlflow", action="store_true", help="do not log the results to MLflow")


def cmd_bench(args: argparse.Namespace) -> None:
    from gns_bench.bench.report import BENCH_ROOT, write_bench_index
    from gns_bench.bench.run import BenchSettings, bench_dir, run_bench

    settings = BenchSettings.quick() if args.quick else BenchSettings()
    settings.device = args.device
    out = args.out or bench_dir(BENCH_ROOT, settings.device)
    run_bench(out, settings, log_to_mlflow=not args.no_mlflow)
    print(out / "README.md")
    if args.out is None:
        print(write_bench_index(BENCH_ROOT))


def _add_ui(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ui", help="serve the MLflow UI on 127.0.0.1")
    p.add_argument("--port", type=int, default=5000, help="port on 127.0.0.1")


def cmd_ui(args: argparse.Namespace) -> None:
    from gns_bench.tracking import serve_ui, tracking_uri, ui_url

    print(f"MLflow UI for {tracking_uri()} at {ui_url(args.port)} (Ctrl-C stops it)", flush=True)
    serve_ui(args.port)


def _add_quickstart(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("quickstart", help="tiny dataset -> short training -> evaluation, all in MLflow (~1 min)")
    p.add_argument("--workdir", type=Path, default=Path("."), help="where data/, runs/ and mlflow.db go")


def cmd_quickstart(args: argparse.Namespace) -> None:
    from gns_bench.config import load_config
    from gns_bench.datasets import ensure_dataset
    from gns_bench.pipeline import train_run
    from gns_bench.tracking import tracking_uri

    args.workdir.mkdir(parents=True, exist_ok=True)
    os.chdir(args.workdir)
    dataset = ensure_dataset("tiny", "smoke", 0)
    print(f"dataset: {dataset.resolve()}")
    config = load_config(CONFIGS / "quickstart.toml")
    out = Path("runs/quickstart")
    summary = train_run(config, dataset, out, experiment="quickstart", run_name="quickstart",
                        resume=(out / "checkpoint.pt").exists())
    _print_summary(summary)
    print(f"MLflow store: {tracking_uri()} (experiment 'quickstart'); browse it with: gns-bench ui")


def _add_stress(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stress", help="stress-test a trained model: long horizons, precision, perturbations, scale",
        description="Runs the tests and generalisation rollouts named by stress.* overrides (default: all four "
                    "tests) on dataset variants of the training domain (datasets/variants/), generated on first "
                    "use, and logs them to MLflow. E.g. stress.tests='[\"horizon\",\"scale\"]' "
                    "stress.scales='[2,8]' stress.generalisation='[\"waterramps-inflow\"]' "
                    "stress.rollout_steps=200")
    p.add_argument("checkpoint", type=Path, help="checkpoint file or run directory")
    p.add_argument("dataset", type=Path, help="the dataset the model was trained on")
    p.add_argument("overrides", nargs="*", help="stress.key=value overrides")
    p.add_argument("--out", type=Path, default=None, help="where figures and curves go (default: the run directory)")
    p.add_argument("--experiment", default="gns-bench", help="MLflow experiment name")
    p.add_argument("--device", default="auto", help="auto (CUDA when present, else CPU), cpu, cuda, cuda:1, ...")


def cmd_stress(args: argparse.Namespace) -> None:
    from gns_bench.pipeline import stress_run

    summary = stress_run(args.checkpoint, args.dataset, args.overrides, out_dir=args.out,
                         experiment=args.experiment, device=args.device)
    print(f"MLflow run: {summary.run_id}")
    print(f"figures and curves: {(summary.out_dir / 'stress').resolve()}")
    for key, value in sorted(summary.metrics.items()):
        if key.startswith("stress/") and key.count("/") >= 2:
            print(f"  {key:48s} {value:.4g}")


def _print_summary(summary) -> None:
    from gns_bench.tracking import ui_url

    if summary.run_id:  # ranks other than 0 of a distributed run log nothing to MLflow
        print(f"MLflow run: {summary.run_id} (after `gns-bench ui`: {ui_url(run_id=summary.run_id)})")
    print(f"run directory: {summary.out_dir.resolve()}")
    for line in summary_lines(summary.metrics):
        print(f"  {line}")


def summary_lines(metrics: dict[str, float]) -> list[str]:
    """The paper's metrics, each beside what it is compared with, over the same steps (the `_moving` figures
    and the rollout steps covered in brackets)."""
    if "rollout_mse" not in metrics:
        return []
    steps = metrics.get("rollout_steps", float("nan"))
    stopped = metrics.get("rollout_stopped", 0.0) > 0
    cv = metrics.get("baseline_cv_same_steps_mse", float("nan"))
    rollout = metrics["rollout_mse"]
    return [f"one-step MSE       {metrics.get('one_step_mse', float('nan')):.4g} (moving particles only: "
            f"{metrics.get('one_step_mse_moving', float('nan')):.4g})",
            f"rollout MSE        {rollout:.4g} over {steps:.0f} steps on average"
            + (" (a monitor stopped some rollouts)" if stopped else "")
            + f" (moving particles only: {metrics.get('rollout_mse_moving', float('nan')):.4g})",
            f"constant velocity  {cv:.4g} over the same steps: GNS / constant velocity = {rollout / cv:.3g}x",
            *physics_lines(metrics)]


def physics_lines(metrics: dict[str, float]) -> list[str]:
    """The physical diagnostics, each against the truth's 1 (gns_bench/evaluate/diagnostics.py)."""
    from gns_bench.evaluate.evaluate import HELD_FALL_STEPS

    nan = float("nan")
    one_step, along = metrics.get("gravity_ratio", nan), metrics.get("rollout_gravity_ratio", nan)
    held = metrics.get("held_gravity_ratio", nan)
    lines = []
    if one_step == one_step or along == along:  # not NaN: some particle was in free fall
        lines.append(f"gravity learned     {one_step:.3g} of g on true windows, {along:.3g} along the rollout "
                     "(1 = the truth's; 0 = blocks that hover)")
    if held == held:
        lines.append(f"held still          {held:.3g} of g for the same particles let go from rest in mid-air "
                     "(near 0: a block the rollout stops there stays)")
    if (fall := metrics.get("held_fall_ratio", nan)) == fall:
        lines.append(f"held, let go        falls {fall:.3g} of the fall at g over its first {HELD_FALL_STEPS} "
                     "steps (1 = the truth's)")
    if (landing := metrics.get("landing_ratio", nan)) == landing:
        lines.append(f"floor learned       {landing:.3g} of the floor's push on landing material, on true windows "
                     "(1 = the truth's; near 0: it falls on through the floor)")
    fall = metrics.get("com_fall_ratio", nan)
    if fall == fall:
        lines.append(f"centre of mass      fell {fall:.3g} of the truth's fall by the rollout's end")
    through = metrics.get("wall_pass_fraction", nan)
    if through == through:
        depth = metrics.get("wall_depth", nan)
        lines.append(f"through a wall      {100 * through:.3g}% of moving particles (the truth: none)"
                     + (f", the deepest {depth:.3g} R beyond it" if depth == depth and through > 0 else ""))
    return lines


def _add_rehash(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rehash", help="record a dataset's current content in its metadata.json (after changing its "
                                      "files on purpose)",
                       description="Runs refuse a dataset whose files no longer match metadata.json's content_hash "
                                   "(a changed dataset would pass for the original in run keys and reports). After "
                                   "changing the files on purpose, this records their hash; the statistics "
                                   "(vel_*, acc_*) are not recomputed.")
    p.add_argument("dataset", type=Path, help=DATASET_HELP)


def cmd_rehash(args: argparse.Namespace) -> None:
    from gns_bench.data.format import read_metadata
    from gns_bench.data.integrity import rehash

    before = read_metadata(args.dataset).content_hash
    after = rehash(args.dataset)
    print(f"{args.dataset}: content_hash {before} -> {after}" if before != after
          else f"{args.dataset}: content_hash unchanged ({after})")


COMMANDS = {
    "generate": (_add_generate, cmd_generate),
    "render": (_add_render, cmd_render),
    "import": (_add_import, cmd_import),
    "train": (_add_train, cmd_train),
    "evaluate": (_add_evaluate, cmd_evaluate),
    "rollout": (_add_rollout, cmd_rollout),
    "sweep": (_add_sweep, cmd_sweep),
    "campaign": (_add_campaign, cmd_campaign),
    "report": (_add_report, cmd_report),
    "stress": (_add_stress, cmd_stress),
    "bench": (_add_bench, cmd_bench),
    "ui": (_add_ui, cmd_ui),
    "quickstart": (_add_quickstart, cmd_quickstart),
    "rehash": (_add_rehash, cmd_rehash),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gns-bench", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for add, _ in COMMANDS.values():
        add(sub)
    return parser


def interrupt_on_signals() -> None:
    """SIGTERM (what SLURM, `kill` and container stops send) acts as Ctrl-C: training checkpoints its last
    step, the MLflow run ends KILLED, and rerunning resumes it. SIGINT is restored too, for runs started in
    the background (`nohup ... &`), where the shell starts them with SIGINT ignored."""

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, interrupt)
        signal.signal(signal.SIGINT, signal.default_int_handler)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    # Overrides may also follow options (`train DATA --out R model.latent_size=64`); anything else is an error.
    stray = [item for item in extra if item.startswith("-") or "=" not in item or not hasattr(args, "overrides")]
    keys = [item for item in stray if not item.startswith("-") and "=" not in item and "." in item]
    if keys and hasattr(args, "overrides"):
        parser.error(f"override {keys[0]!r} has no value: overrides are section.key=value, e.g. {keys[0]}=1000")
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = [*args.overrides, *extra]
    try:
        COMMANDS[args.command][1](args)
    except (DatasetError, ConfigError, FileExistsError, FileNotFoundError, NotADirectoryError, ValueError,
            RuntimeError) as exc:
        print(f"gns-bench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gns-bench {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


def run() -> int:
    """The `gns-bench` command: `main` with the signal handling a long-running process needs."""
    interrupt_on_signals()
    return main()


if __name__ == "__main__":
    sys.exit(run())
