"""Deprecated: the baselines now live in :mod:`zernet.nn.models.baselines` and :mod:`zernet.nn.models.paper`."""

from zernet.nn.models.baselines import FeaStNet
from zernet.nn.models.paper import PaperZernikeConv, PaperZerNet, ridge_normal_matrix

__all__ = ["FeaStNet", "PaperZernikeConv", "PaperZerNet", "ridge_normal_matrix"]
