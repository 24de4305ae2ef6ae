"""Shared fixtures: the repository's scenario and small grids."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from dswm.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
LEARNING_BASELINES = {"ppo": "model-free RL", "sac": "model-free RL", "maddpg": "MARL", "ga_matr": "MARL",
                      "tdmpc": "model-based", "emorl_tcto": "multi-obj. RL",
                      "hrl_tpra": "hier. RL"}
"""The paper's learning baselines with their Table III class; each trains alone (no other method shares its model)."""



@pytest.fixture(autouse=True)
def one_thread():
    """Tests use small tensors: one torch thread is fastest, and immune to a busy machine's oversubscription
    (code under test may set its own thread count; it is restored after each test)."""
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def scenario():
    """The scenario of config.yaml (u: the demo calibration, DEMO_INTENSITY, where config.yaml says calibrate)."""
    return load_scenario(ROOT / "config.yaml", standin=True)


@pytest.fixture
def make_scenario(scenario):
    """The config scenario with some constants replaced."""
    def make(**changes):
        return dataclasses.replace(scenario, **changes)
    return make


def dataset_of(config: dict, dataset: str):
    """The typed ``datasets.<dataset>`` section of a config mapping."""
    from prep.config import dataset_from_plain

    return dataset_from_plain(dataset, config["datasets"][dataset])


def prepare_from_config(config: dict, dataset: str, **kwargs):
    """``prep.pipeline.prepare_dataset`` with the typed sections of a config mapping."""
    from prep.config import common_from_plain
    from prep.pipeline import prepare_dataset

    return prepare_dataset(dataset_of(config, dataset), common_from_plain(config["datasets"]["common"]), dataset,
                           **kwargs)
