import os

# DEEPMAPPING_TEST_THREADS=2 runs every test with 2 torch/OpenMP threads (the suite must pass with
# either: CI machines differ in thread count; docs/conventions.md "Tests")
THREADS = int(os.environ.get("DEEPMAPPING_TEST_THREADS", "1"))
os.environ.setdefault("OMP_NUM_THREADS", str(THREADS))  # Open3D (3D baselines) would use every core under pytest -n 2

import pytest  # noqa: E402  (after the thread settings above)
import torch  # noqa: E402

torch.set_num_threads(THREADS)  # tests run in parallel (pytest -n 2): one thread each by default


@pytest.fixture(autouse=True)
def _torch_threads():
    """Every test starts with THREADS torch threads: a run with ``threads`` set (register's cfg.threads)
    changes the process's count, and a test after it in the same worker would otherwise inherit it
    (seen: the kill -9 resume test with 2 threads, in a shuffled order, resumed on 1 thread)."""
    torch.set_num_threads(THREADS)


@pytest.fixture(scope="session")
def indoor_map():
    from deepmapping.sim.maps import procedural_indoor_map

    return procedural_indoor_map(0)


@pytest.fixture(scope="session")
def small_scans(indoor_map):
    """32 simulated scans x 256 beams (px/512 units) with ground truth."""
    from deepmapping.sim.dataset import simulate

    return simulate(indoor_map, 32, seed=1)


@pytest.fixture(scope="session")
def sim_folder(tmp_path_factory, indoor_map, small_scans):
    from deepmapping.sim.dataset import write_authors_layout

    out = tmp_path_factory.mktemp("sim") / "traj"
    write_authors_layout(out, small_scans, occ=indoor_map)
    return out
