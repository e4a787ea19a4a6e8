"""Shared test helpers: compose the real Hydra configs, tiny budgets, temporary stores."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from cdqn.config import register_configs  # cdqn sets NUMBA_CACHE_DIR; numba is not imported

if worker := os.environ.get("PYTEST_XDIST_WORKER"):
    # numba reads its cache index, adds an entry and writes it back without a lock: two processes
    # compiling one function for different argument types at once can leave the index pointing
    # at the other's machine code (numba issue 10128).  Each pytest-xdist worker, and every
    # command its tests start (they inherit the variable), compiles into a folder of its own
    # under cdqn's; numba reads the variable once, when it is imported
    assert "numba" not in sys.modules, "NUMBA_CACHE_DIR is set too late"
    os.environ["NUMBA_CACHE_DIR"] = str(Path(os.environ["NUMBA_CACHE_DIR"]) / worker)

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
TINY = ["network.width=32", "train.episodes=3", "train.progress=false"]
"""Overrides that make a training run take well under a second."""

register_configs()


def compose_config(overrides: list[str] | None = None) -> DictConfig:
    """The configuration ``python -m cdqn.train <overrides>`` would run."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides or []))


@pytest.fixture(scope="session", autouse=True)
def working_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Every test, and every module fixture, runs in a folder of its own test process (a
    pytest-xdist worker), not in the checkout: what cdqn and MLflow write relative to the
    working folder (a SQLite store's artifacts in ``./mlruns``, ``./outputs``, ``./multirun``,
    ``./checkpoints``) stays out of the checkout and apart from the other workers'."""
    folder = tmp_path_factory.mktemp("cwd")
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        yield folder


@pytest.fixture
def tracking_uri(tmp_path: Path) -> str:
    """A fresh embedded MLflow store for one test."""
    return f"sqlite:///{tmp_path / 'mlflow.db'}"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` first: with the suite spread over worker processes (pytest-xdist,
    a file at a time to whichever worker is free) the files with long tests start early and
    the many short ones fill the gaps, instead of one long file running alone at the end."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
