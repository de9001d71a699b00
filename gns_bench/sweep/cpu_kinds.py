"""Which kind of machine a run trains on, and which runs wait for another kind.

The verdicts compare runs on one CPU kind only (report/verdict.py): bf16 products differ between an Intel
Xeon's AMX tiles and an AMD EPYC's AVX-512 BF16 units, and so do the step rates the reports' time columns show.
A campaign goes on on whatever machine a session gets, so the runner holds

- every run of a sweep whose runs are compared with each other (an ablation's arms, a study's candidates:
  `COMPARED`) to the kind most of its runs trained on so far (an ablation's default arm, shared from the
  domain sweep, counts where it trained), and
- a run that began training and resumes from its checkpoint to the kind it began on,

and runs anything else anywhere, except that a run set to train in bf16 (above the smoke tier, whose runs take
seconds) waits for a machine whose bf16 products outrun its fp32 ones (`autotune.matmul_rates`): where they do
not, the machine has no bf16 unit and the run would train several times slower than in fp32, and a tier's
precision is fixed so that its results do not depend on the machine. `--any-cpu-kind` (`gns-bench sweep`,
`gns-bench campaign`) lifts every hold.
A kind is the CPU's family, model and stepping (`devices.cpu_identity`: "AMD EPYC" names two generations
whose step rates differ), the model name where /proc/cpuinfo says nothing, or the GPU's name.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # reports read kinds without torch
    import torch

COMPARED = ("ablation", "study")  # sweep kinds whose runs are compared with each other
WAITS = "waits for a machine"  # the status of a run held to another kind of machine


def kind_of(tags: Mapping[str, str]) -> str:
    """The kind of machine a run's environment tags (`tracking.environment_tags`) name; "" where none. The
    `cpu` tag's clock ("2596 MHz") is left out: /proc/cpuinfo reports the current frequency, which moves on a
    machine that scales it, and one kind of CPU must not become two."""
    if str(tags.get("device", "cpu")).startswith("cuda"):
        return tags.get("hardware", "")
    identity = ", ".join(part for part in tags.get("cpu", "").split(", ") if part and not part.endswith(" MHz"))
    return identity or tags.get("hardware", "")


def kind_here(device: torch.device) -> str:
    """This machine's kind, as `kind_of` reads it from the tags a run trained here would carry."""
    from gns_bench.devices import cpu_identity
    from gns_bench.tracking import hardware_description

    return kind_of({"device": str(device), "hardware": hardware_description(str(device)), "cpu": cpu_identity()})


def held_kind(kinds: Iterable[str]) -> str:
    """The kind most of `kinds` name (the first to get there on a tie, so pass them in start order); "" for none."""
    counts = Counter(kind for kind in kinds if kind)
    if not counts:
        return ""
    most = max(counts.values())
    return next(kind for kind in counts if counts[kind] == most)


def waiting_status(kind: str, why: str) -> str:
    return f"{WAITS} of CPU kind {kind} ({why})"


def waiting_for_bf16(rates_described: str) -> str:
    return f"{WAITS} with a bf16 unit (it trains in bf16, and {rates_described})"
