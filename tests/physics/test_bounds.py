"""Every array access of the Taichi solvers stays in bounds: each solver run briefly in a process with
Taichi's debug mode on (`GNS_BENCH_TAICHI_DEBUG=1`), which checks every field and ndarray index.

Without it an out-of-bounds read is silent, or a segfault that depends on where the array was allocated:
`v[j] if j >= 0 else ...` in a kernel loads `v[-1]` for a wall neighbour (Taichi evaluates both branches
of a conditional expression), which crashed cpu-tier WATER-3D generation a few times in a hundred trajectories.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

_PRELUDE = "import numpy as np\n"
_SCRIPTS = {
    # SPH: water resting on the floor of a narrow box, so that every kernel meets wall neighbours
    "sph": """
from gns_bench.physics.sph import SPHParams, run_sph
from gns_bench.physics.sph_scene import fluid_lattice
box = np.array([[0.0, 0.2], [0.0, 0.4], [0.0, 0.2]])
points = np.stack(np.meshgrid(*fluid_lattice(box, 0.025), indexing="ij"), -1).reshape(-1, 3)
position = points[points[:, 1] < 0.1].astype(np.float32)
params = SPHParams(bounds=box, gravity=(0.0, -9.81, 0.0), particle_spacing=0.025)
frames, _ = run_sph(params, position, np.zeros_like(position), 5, 0.0025)
print("frames", frames.shape[0])
""",
    # PBD and MPM: one smoke-tier trajectory of a domain each
    "pbd": "domain = 'boxbath'\n",
    "mpm": "domain = 'goop'\n",
}
_SMOKE = """
import importlib
from gns_bench.physics.generate import SOLVER_MODULES
from gns_bench.physics.spec import load_domain_spec
spec = load_domain_spec(domain)
solver = importlib.import_module(SOLVER_MODULES[spec.solver])
trajectory = solver.simulate(spec.for_trajectory("train", 0), "smoke", np.random.default_rng(0))
print("frames", trajectory.position.shape[0])
"""


@pytest.mark.parametrize("solver", ["sph", "pbd", "mpm"])
def test_solver_reads_and_writes_in_bounds(solver: str, tmp_path) -> None:
    script = _PRELUDE + _SCRIPTS[solver] + ("" if solver == "sph" else _SMOKE)
    # Taichi's own cache directory: kernels compiled without bounds checks are not reused here.
    env = {**os.environ, "GNS_BENCH_TAICHI_DEBUG": "1", "GNS_BENCH_TAICHI_ARCH": "cpu",
           "TI_OFFLINE_CACHE_FILE_PATH": str(tmp_path / "ticache")}
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert out.returncode == 0, f"{solver} under Taichi's debug mode:\n{out.stderr[-3000:]}"
    assert out.stdout.strip().splitlines()[-1].startswith("frames ")
