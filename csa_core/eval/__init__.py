"""Evaluation: segmentation scores per scene and continual-learning scores over scenes."""

from csa_core.eval.continual import continual_metrics
from csa_core.eval.miou import ConfusionMatrix, evaluate_label_folders, format_miou_table

__all__ = ["ConfusionMatrix", "continual_metrics", "evaluate_label_folders", "format_miou_table"]
