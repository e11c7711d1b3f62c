import os
import shutil
import tempfile
import zlib  # noqa: F401  load before pycolmap (pycolmap first makes zlib corrupt the heap)

WORKER = bool(os.environ.get("PYTEST_XDIST_WORKER"))
if WORKER:
    # `make test` runs two workers on two cores: one thread each (and in the commands the tests start), as two
    # jobs on two threads each slow each other many times over; set before numpy's BLAS reads them
    os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")

import cv2  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

# One scratch folder for the whole session (shared surveys, matplotlib's cache), removed when it ends.
SCRATCH = tempfile.mkdtemp(prefix="watergan-tests-")
os.environ.setdefault("MPLCONFIGDIR", os.path.join(SCRATCH, "mpl"))
if WORKER:
    torch.set_num_threads(1)
    cv2.setNumThreads(1)

from watergan.formation import FormationState, pixel_grid  # noqa: E402


@pytest.fixture(autouse=True)
def _release_workspace_locks():
    """Each test's in-process runs give up their workspaces' locks when it ends (a process holds them until it
    exits), so the session holds no more open lock files than one test needs."""
    yield
    from pipeline.workspace import release_workspaces

    release_workspaces()


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(SCRATCH, ignore_errors=True)


def make_state(batch: int = 2, height: int = 6, width: int = 8, dtype=torch.float64, seed: int = 0,
               range_m: float | None = None) -> FormationState:
    """A small state with every field filled, scene 1.5-4 m away, as the simulator would give."""
    g = torch.Generator().manual_seed(seed)
    rand = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    rng = (1.5 + 2.5 * rand(batch, 1, height, width)) if range_m is None else \
        torch.full((batch, 1, height, width), float(range_m), dtype=dtype)
    uv = pixel_grid(height, width, batch, dtype)
    ray = torch.cat([(uv - 0.5) * torch.tensor([1.2, 0.9], dtype=dtype).view(1, 2, 1, 1),
                     torch.ones(batch, 1, height, width, dtype=dtype)], dim=1)
    ray = ray / ray.norm(dim=1, keepdim=True)
    points = ray * rng
    normals = torch.nn.functional.normalize(torch.tensor([0.1, -0.2, -1.0], dtype=dtype).view(1, 3, 1, 1)
                                            + 0.1 * rand(batch, 3, height, width), dim=1)
    world = points * torch.tensor([1.0, -1.0, -1.0], dtype=dtype).view(1, 3, 1, 1)
    return FormationState(
        direct=0.05 + 0.9 * rand(batch, 3, height, width),
        range_m=rng,
        pixel_uv=uv,
        image_wh=(width, height),
        depth_m=points[:, 2:3],
        points_cam=points,
        normals_cam=normals,
        points_world=world,
        normals_world=normals * torch.tensor([1.0, -1.0, -1.0], dtype=dtype).view(1, 3, 1, 1),
        water_depth_m=20.0 - world[:, 2:3],
        frame_index=torch.arange(batch) + 3,
        z=rand(batch, 100) * 2 - 1,
        valid=torch.ones(batch, 1, height, width, dtype=torch.bool),
    )


@pytest.fixture
def state():
    return make_state()
