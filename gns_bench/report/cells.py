"""Table cells and the budget statement: how a report words a set of runs (`RunRow`s).

Shared by the sweep reports (`report.py`) and the stability report (`stability.py`); numbers print with
three significant digits, gaps as "—", and a row with no finished run as MISSING.
"""

from __future__ import annotations

import math
from collections import Counter

from gns_bench.report.collect import RunRow, mean_std
from gns_bench.report.reference import paper_training_steps

MISSING = "**missing**"

# The physical diagnostics every evaluation logs (`evaluate/diagnostics.py`), with their column headings, in the
# order the domain table and the study tables show them.
DIAGNOSTIC_COLUMNS = (("gravity_ratio", "gravity ratio, one step"), ("held_gravity_ratio", "held still"),
                      ("held_fall_ratio", "held still, fall over 10 steps"),
                      ("rollout_gravity_ratio", "gravity ratio, rollout"),
                      ("landing_ratio", "floor's push, one step"),
                      ("com_fall_ratio", "centre-of-mass fall, ours / truth"),
                      ("wall_pass_fraction", "particles through a wall"),
                      ("wall_depth", "deepest beyond a wall (R)"),
                      ("steps_before_trip", "steps before a monitor's first trip"))


def fmt(value: float) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.3g}"


def mean_cell(mean: float, std: float, count: int) -> str:
    """"mean ± sample std" over seeds; the mean alone from one seed (a spread needs two)."""
    if not count:
        return MISSING
    return fmt(mean) + (f" ± {fmt(std)}" if count > 1 else "")


def times(value: float) -> str:
    """A ratio already divided: "0.436x", or "—" when missing."""
    return fmt(value) if fmt(value) == "—" else f"{fmt(value)}x"


def ratio(ours: float, paper: float | None) -> str:
    if paper is None or not math.isfinite(ours) or paper == 0:
        return "—"
    return f"{ours / paper:.3g}x"


def status_cell(rows: list[RunRow]) -> str:
    if not rows or not any(r.ok for r in rows):
        states = sorted({r.status for r in rows}) or ["missing"]
        return "**" + ", ".join(states) + "**"
    bad = [r for r in rows if not r.ok]
    return "ok" if not bad else f"ok ({len(bad)} of {len(rows)} {', '.join(sorted({r.status for r in bad}))})"


def run_id_cell(row: RunRow) -> str:
    """The run id, with its status when it did not finish, and the run it copies when another sweep trained it."""
    if not row.run_id:
        return "—"
    source = row.tag("shared_from")
    return (f"`{row.run_id}`" + ("" if row.ok else f" ({row.status})")
            + (f", shared from {row.tag('shared_from_run', '?')} (`{source}`)" if source else ""))


def run_ids_cell(rows: list[RunRow]) -> str:
    return "<br>".join(run_id_cell(r) for r in rows if r.run_id) or "—"


def comparable_cv(row: RunRow) -> float:
    """The constant-velocity rollout MSE over the steps this run's GNS rollouts covered: the whole horizon, or
    the steps before a monitor's stop; NaN for a stopped run evaluated before that was logged."""
    same_steps = row.metric("baseline_cv_same_steps_mse")
    if math.isfinite(same_steps):
        return same_steps
    return math.nan if row.metric("rollout_stopped") > 0 else row.metric("baseline_cv_rollout_mse")


def any_stopped(rows: list[RunRow]) -> bool:
    """Whether a health monitor stopped some rollout of any of `rows` (NaN, for a run that did not finish, is not)."""
    return any(r.metric("rollout_stopped") > 0 for r in rows)


def relative_to_cv(row: RunRow) -> float:
    """A run's rollout MSE over constant velocity's on the same steps: like for like whether or not a monitor
    stopped its rollouts (a rollout stopped early has a raw rollout MSE over few steps, which reads low), so what
    the budget study ranks candidates by and the baselines report compares models by. NaN where unknown."""
    baseline = comparable_cv(row)
    return row.metric("rollout_mse") / baseline if baseline > 0 else math.nan


def _paired_with_cv(rows: list[RunRow]) -> list[RunRow]:
    """The runs whose constant-velocity MSE over the GNS rollouts' own steps is known."""
    return [r for r in rows if comparable_cv(r) > 0]  # NaN (not finished, not logged) fails the test


def cv_ratio(rows: list[RunRow]) -> str:
    """GNS / constant-velocity rollout MSE (means over runs) printed beside the two numbers it divides, both
    over the same steps: "0.38x (0.034 / 0.091)"; "—" where unknown."""
    paired = _paired_with_cv(rows)
    if not paired:
        return "—"
    gns = mean_std([r.metric("rollout_mse") for r in paired])[0]
    cv = mean_std([comparable_cv(r) for r in paired])[0]
    return f"{ratio(gns, cv)} ({fmt(gns)} / {fmt(cv)})"


def against_cv(rows: list[RunRow]) -> str:
    """`cv_ratio`, saying when the steps compared end where a monitor stopped the GNS rollouts."""
    paired = _paired_with_cv(rows)
    if not paired:
        return "GNS rollouts stopped" if any_stopped(rows) else "—"
    return cv_ratio(paired) + (", over the steps before the stops"
                               if any_stopped(paired) else "")


def steps_covered(rows: list[RunRow]) -> str:
    """Mean number of steps the finished runs' rollouts covered (± the sample std over runs, where they differ:
    the spread the rollout-length verdict's band comes from), and the share a monitor stopped."""
    steps, std, n = mean_std([r.metric("rollout_steps") for r in rows])
    if not n:
        return MISSING if not any(r.ok for r in rows) else "—"
    stopped = mean_std([r.metric("rollout_stopped") for r in rows])[0]
    spread = f" ± {std:.0f}" if std > 0 else ""  # every run over the whole horizon: no spread to show
    return f"{steps:.0f}{spread}" + (f" ({stopped:.0%} stopped)" if stopped > 0 else "")


def used_precision(row: RunRow) -> str:
    """What the run trained in: the settings `train.precision`/`train.compile = "auto"` chose (tags), else the
    config's."""
    precision = row.tag("train/precision_used") or row.param("train.precision", "fp32")
    compiled = (row.tag("train/compile_used") or row.param("train.compile")) == "True"
    auto = "auto" in (row.param("train.precision"), row.param("train.compile"))
    return precision + (" compiled" if compiled else "") + (" (auto)" if auto else "")


def budget(rows: list[RunRow]) -> str:
    """Training steps, wall time, hardware and dataset tier of the finished runs in a row."""
    done = [r for r in rows if r.ok]
    if not done:
        return "—"
    steps = sorted({int(float(r.param("train.steps", "0"))) for r in done})
    wall = mean_std([r.metric("train/wall_time_s") for r in done])[0]
    hardware = machines(done)
    tiers = sorted({r.tag("dataset_tier") or r.param("sweep.dataset_tier", "?") for r in done})
    horizon = mean_std([r.metric("rollout_steps") for r in done])[0]
    models = sorted({f"M={r.param('model.message_passing_steps', '?')}, latent {r.param('model.latent_size', '?')}"
                     for r in done})
    # fp32 (the paper's) unless a run trained in reduced precision; torch.compile changes speed, not the function
    precisions = sorted({used_precision(r) for r in done})
    if precisions != ["fp32"]:
        models = [f"{m}, {'/'.join(precisions)}" for m in models]
    # Where the schedule stood at the last step: short runs on the paper's 5M-step decay end at ~1e-4, and
    # their last weights are a noisy snapshot (sweeps/tiers.toml, small tier)
    final_rates = sorted({fmt(lr) for lr in (r.metric("learning_rate") for r in done) if math.isfinite(lr)})
    if final_rates:
        models = [f"{m}, final learning rate {'/'.join(final_rates)}" for m in models]
    return (f"{'/'.join(f'{s:,}' for s in steps)} steps of a GNS with {' / '.join(models)}, {fmt(wall)} s, "
            f"{hardware}, data tier {'/'.join(tiers)}, rollouts of {fmt(horizon)} steps in {rollout_precision(done)}")


def rollout_precision(rows: list[RunRow]) -> str:
    """What the network's rollouts ran in (`eval.precision`): the reported numbers' precision."""
    return "/".join(sorted({r.param("eval.precision", "fp32") for r in rows})) or "—"


SMOKE_NOTICE = ("**Smoke tier: a pipeline check, not a result.** Tiny models trained for a few steps on tiny "
                "datasets show that generation, training, evaluation, tracking and reporting run end to end; "
                "their numbers mean nothing, so this report compares none of them with the paper and draws no "
                "conclusion.")

# Every metric a report shows, defined once at its top (the paper's definitions first: Sec. 4.4, App. B.4).
METRIC_DEFINITIONS = [
    "**one-step MSE**: squared error of the predicted next position from clean inputs, averaged over every "
    "particle (kinematic ones included), dimension and window of the test split; position units² (the box is "
    "about 1 wide). The release's definition (learning_to_simulate/train.py), which the paper's Table 1 reports.",
    "**rollout MSE**: squared position error of a rollout fed its own predictions, averaged over the release's "
    "`sequence_length - 6` steps, every particle (kinematic ones follow the data and add 0) and dimension; mean "
    "over test trajectories. When a health monitor stopped a rollout, over the steps before the stop: then the "
    "table says over how many, and sets no ratio to the paper's whole-rollout figure beside it.",
    "**MSE, rollout steps 1-10**: the rollout MSE over its first 10 steps, which every rollout reaches: the same "
    "steps for every run and domain (LagrangeBench's habit of fixed horizons).",
    "**GNS / constant velocity**: rollout MSE divided by that of extrapolating every particle at its last "
    "velocity over the same trajectories and steps, printed as ratio (GNS / baseline); below 1x the model beats "
    "the trivial baseline.",
    "**OT**: exact earth mover's distance W2² between the predicted and true clouds of moving particles "
    "(squared Euclidean cost, uniform weights, POT's `emd2`; position units²), mean over 10 evenly spaced "
    "rollout steps; App. B.4.",
    "**MMD**: squared maximum mean discrepancy between the same clouds, Gaussian kernel of width 2 R (R the "
    "connectivity radius), biased V-statistic; App. B.4.",
    "**KE error**: sum over the rollout of |kinetic energy predicted - true| over the sum of the true kinetic "
    "energy (mean over moving particles, unit mass, velocities per stored frame); 0 = the energy history "
    "reproduced, 1 = e.g. a rollout that froze.",
]


SHARED_CORES = "(shared cores)"


def run_cpu_generation(row: RunRow) -> str:
    """The CPU family and model a run recorded (`devices.cpu_identity`), e.g. "family 25, model 17"; "" for a GPU
    run or one from before the tag."""
    identity = dict(part.split(" ", 1) for part in row.tag("cpu").split(", ") if " " in part)
    if row.tag("device", "cpu") != "cpu" or not {"family", "model"} <= identity.keys():
        return ""
    return f"family {identity['family']}, model {identity['model']}"


def machines(rows: list[RunRow]) -> str:
    """Every machine the rows ran on, "; "-separated ("" for none): each `hardware` tag (model name and threads,
    or the GPU) once, with the CPU generations its runs recorded, counted where there are several. "AMD EPYC"
    names more than one generation, and the campaign's runs came from two whose step rates differ
    (reports/NOTES.md)."""
    by_hardware: dict[str, Counter[str]] = {}
    for row in rows:
        by_hardware.setdefault(row.tag("hardware", "?"), Counter())[run_cpu_generation(row)] += 1
    cells = []
    for hardware, generations in sorted(by_hardware.items()):
        if set(generations) == {""}:
            cells.append(hardware)
        elif len(generations) == 1:
            cells.append(f"{hardware} (CPU {next(iter(generations))})")
        else:
            counts = "; ".join(f"{generation or 'not recorded'}: {n} run{'s' * (n > 1)}"
                               for generation, n in sorted(generations.items(), key=lambda g: (not g[0], g[0])))
            cells.append(f"{hardware} (CPU {counts})")
    return "; ".join(cells)


def shared_cores(row: RunRow) -> str:
    """How another job competed for the cores while the run trained (its `train/oversubscribed` tag, written by
    `train.loop.LoadWatch`); "" when it had them to itself. Such a run's training time reads high."""
    return row.tag("train/oversubscribed") or ""


def shared_cores_mark(rows: list[RunRow]) -> str:
    """` (shared cores)`, to follow a training time that any of `rows` measured with its cores shared; else ""."""
    return f" {SHARED_CORES}" if any(shared_cores(r) for r in rows) else ""


def _which(runs: list[RunRow], done: list[RunRow]) -> str:
    """A caveat's opening: 'In every run (6 of 6)' or 'In 2 of 6 runs'."""
    if len(runs) == len(done):
        return f"In every run ({len(runs)} of {len(done)})"
    return f"In {len(runs)} of {len(done)} runs"


def _named(runs: list[RunRow], done: list[RunRow]) -> str:
    """The runs' IDs, where they are some of the runs (the report's tables give every run's ID)."""
    return "" if len(runs) == len(done) else f": {', '.join(f'`{r.run_id}`' for r in runs)}"


def budget_statement(rows: list[RunRow], tier: str = "") -> str:
    """Once, at the top of a report: what the runs cost (tier, steps, precision, hardware, training time, data)
    in one sentence, then one bullet per caveat that applies (the plain-words reading of gaps to the paper,
    rollouts cut, stopped or flagged, shared cores, older runs, our own ground truth), naming the runs a caveat
    concerns when it concerns only some. At the smoke tier, only that it is a pipeline check."""
    if tier == "smoke":
        return SMOKE_NOTICE
    done = [r for r in rows if r.ok]
    paper = paper_training_steps()
    if not done:
        return "No finished run: nothing to compare with the paper yet."
    steps = max(int(float(r.param("train.steps", "0"))) for r in done)
    final = sorted({int(r.metric("train/final_step")) for r in done if math.isfinite(r.metric("train/final_step"))})
    trained = final or [steps]
    fraction = max(trained) / paper
    wall = [r.metric("train/wall_time_s") for r in done if math.isfinite(r.metric("train/wall_time_s"))]
    hardware = machines(done)
    precisions = "/".join(sorted({used_precision(r) for r in done}))
    data = "/".join(sorted({r.tag("dataset_tier") or r.param("sweep.dataset_tier") or "?" for r in done}))
    head = (f"**Budget{f' ({tier} tier)' if tier else ''}.** {len(done)} finished run(s): "
            f"{_span(trained)} training steps of batch 2 ({100 * fraction:.2g}% of the paper's {paper:,} at most), "
            f"{precisions}, {fmt(sum(wall) / 3600) if wall else '?'} h of training in all"
            f" ({fmt(min(wall) / 60) if wall else '?'}-{fmt(max(wall) / 60) if wall else '?'} min a run) on "
            f"{hardware}; data tier {data}.")
    caveats = []
    if fraction < 0.01:
        caveats.append("**Far below the paper's budget**, so gaps to its figures are expected; a number at or "
                       "below the paper's is on our own, smaller test set (like scenes, not its trajectories) and "
                       "does not show that its accuracy is reproduced.")
    elif fraction < 1:
        caveats.append("**Below the paper's budget**: remaining gaps to the paper are expected from the shorter "
                       "training and smaller datasets.")
    capped = sorted({r.param("eval.rollout_steps") for r in done} - {"", "None"}, key=float)
    if capped:
        caveats.append(f"**Rollouts cut** at `eval.rollout_steps` = {'/'.join(capped)} steps, where the paper rolls "
                       "out whole trajectories (K = 150 to 2000 steps): errors grow along a rollout, so these "
                       "rollout MSEs are not comparable with the paper's (they typically sit below them).")
    stopped = [r for r in done if r.metric("rollout_stopped") > 0]
    if stopped:
        caveats.append(f"**Stopped rollouts.** {_which(stopped, done)} a health monitor stopped some rollouts early "
                       f"(MLflow tag `<split>/rollouts_stopped` says where and why{_named(stopped, done)}); their "
                       "rollout MSE covers only the steps before the stop, and the constant-velocity baseline "
                       "beside it covers the same steps.")
    flagged = [r for r in done if r.metric("rollout_flagged") > 0]
    if flagged:
        caveats.append(f"**Flagged rollouts.** {_which(flagged, done)} a monitor outside `eval.stop_on` flagged "
                       "some rollouts (by default: a particle out of the bounds) and they ran on, as the paper's do: "
                       "the rollout MSE counts that error (MLflow tag `<split>/rollouts_flagged` says "
                       f"where{_named(flagged, done)}).")
    shared = [r for r in done if shared_cores(r)]
    if shared:
        where = "; ".join(f"`{r.run_id}`: {shared_cores(r)}" for r in shared)
        caveats.append(f"**Shared cores.** {_which(shared, done)} another job competed for the cores during "
                       f"training (MLflow tag `train/oversubscribed`; {where}): their training times read high, "
                       f"marked `{SHARED_CORES}` in the tables.")
    legacy = [r for r in done if not math.isfinite(r.metric("rollout_mse_moving"))]
    if legacy:
        caveats.append(f"**Older runs.** {_which(legacy, done)} the evaluation predates the release's definitions"
                       f"{_named(legacy, done)}. Their MSEs leave kinematic particles out "
                       "and their rollout MSE covers one step more (it reads higher by up to N_all / N_moving on "
                       "domains with obstacles), and their model summed the updated edges "
                       "(`model.aggregate = \"updated_edges\"`).")
    if any(r.tag("dataset_tier") for r in done):  # set by gns-bench's generators; imported datasets have none
        caveats.append("**Our own ground truth.** The ground truth comes from gns-bench's own solvers "
                       "(`datasets/<domain>.toml`), in the paper's format and units but not its trajectories: the "
                       "paper's numbers are a reference on like scenes, not on the same test set.")
    return "\n".join([head, "", *(f"- {c}" for c in caveats)]) if caveats else head


def _span(values: list[int]) -> str:
    low, high = min(values), max(values)
    return f"{low:,}" if low == high else f"{low:,}-{high:,}"


def definitions_section() -> list[str]:
    from gns_bench.evaluate import registry

    return ["## Metrics", "", *(f"- {line}" for line in [*METRIC_DEFINITIONS, *registry.definitions()]), ""]
