"""Shared fixtures: the shipped pad, a private operator cache, the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"


def pytest_configure(config):
    """Command output is rendered 240 columns wide, so that long temporary paths in error messages
    are not folded mid-name. With several xdist workers, each worker's numerical libraries use one
    thread: the workers already keep every core busy, and two OpenMP pools per core stall each
    other."""
    os.environ["COLUMNS"] = "240"
    workers = getattr(config.option, "numprocesses", None)
    if workers and workers != 1:
        for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(name, "1")


def pytest_collection_modifyitems(config, items):
    """Modules with more tests marked ``slow`` run first, each module's tests in their own order:
    with ``--dist loadscope`` the long modules start at once on the workers and the short ones
    fill in behind them, instead of one long module running alone at the end."""
    order = {}
    for item in items:
        weight = order.setdefault(item.module.__name__, [len(order), 0])
        weight[1] += item.get_closest_marker("slow") is not None
    items.sort(key=lambda it: (-order[it.module.__name__][1], order[it.module.__name__][0]))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the checkout; fails (does not skip) when it is missing."""
    if not SHARED_DATA.is_dir():
        pytest.fail(
            f"shared data folder {SHARED_DATA} not found: the tests need ../shared/data beside "
            f"the repository (real ball presses and indenter STLs)"
        )
    return SHARED_DATA


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory):
    """Operators and envelope grids go to a fresh cache: tests never read a user's cache."""
    folder = tmp_path_factory.mktemp("tactile_deploy_cache")
    old = os.environ.get("TACTILE_DEPLOY_CACHE_DIR")
    os.environ["TACTILE_DEPLOY_CACHE_DIR"] = str(folder)
    yield folder
    if old is None:
        os.environ.pop("TACTILE_DEPLOY_CACHE_DIR", None)
    else:
        os.environ["TACTILE_DEPLOY_CACHE_DIR"] = old


@pytest.fixture(scope="session")
def pad():
    from tactile_deploy.pad.asset import load_pad

    return load_pad()


@pytest.fixture(scope="session")
def pad_sim(pad):
    """The shipped pad, nu = 0.48, frictionless, surface operators computed once per session."""
    from tactile_deploy.simulation.contact import get_simulator
    from tactile_deploy.fem.material import Material

    sim = get_simulator(Material(nu=0.48))
    sim.prepare()
    return sim


@pytest.fixture(scope="session")
def small_sim():
    """A small pad (r 10 mm, 1,735 nodes), nu = 0.48, frictionless: fast discrepancy tests."""
    from tactile_deploy.fem.material import Material
    from tactile_deploy.fem.simulator import ContactSimulator
    from tactile_deploy.pad.geometry import PadGeometry
    from tactile_deploy.pad.mesh import build_pad_mesh

    mesh = build_pad_mesh(PadGeometry(name="small", radius_mm=10.0, edge_mm=1.0, n_layers=4))
    sim = ContactSimulator(mesh, Material(nu=0.48))
    sim.prepare()
    return sim


@pytest.fixture(scope="session")
def sims(small_sim):
    """(the small pad's frictionless simulator, the same pad and material with sticking friction),
    each prepared once: the friction tests' pair."""
    from tactile_deploy.fem.simulator import ContactSimulator

    stick = ContactSimulator(small_sim.mesh, small_sim.material.model_copy(
        update={"friction": "stick"}), use_cache=False)
    stick.prepare()
    return small_sim, stick


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module: on a shared 2-core machine two OpenMP threads stall behind
    other processes (adaptation steps measured 0.7 s with one thread, 2.5-20 s with two)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
