"""Evaluation metrics of the paper's Tables 1 and 3, plus collision rate, physics energy and
an error's split into a static drape and dynamics (:mod:`garmentgnn.metrics.split`)."""
from garmentgnn.metrics.garment_metrics import (METRIC_UNITS, collision_rate, curvature_error,
                                                edge_length_error, evaluate, evaluate_inputs,
                                                face_normal_error, physics_energy,
                                                vertex_distance, vertex_normal_error)
from garmentgnn.metrics.split import split_inputs, static_dynamic_split

__all__ = ["METRIC_UNITS", "collision_rate", "curvature_error", "edge_length_error", "evaluate",
           "evaluate_inputs", "face_normal_error", "physics_energy", "split_inputs",
           "static_dynamic_split", "vertex_distance", "vertex_normal_error"]
