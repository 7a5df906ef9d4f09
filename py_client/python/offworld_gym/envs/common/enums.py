"""Experiment options of real envs (the original's enums)."""

from enum import Enum


class LearningType(str, Enum):
    """How the agent learns; stored with the experiment."""

    END_TO_END = "end2end"
    SIM_2_REAL = "sim2real"
    HUMAN_DEMOS = "humandemos"


class AlgorithmMode(str, Enum):
    """Train or test; test runs count for the leaderboard."""

    TRAIN = "train"
    TEST = "test"
