"""Evaluation metrics of the paper's Tables 1 and 3, plus collision rate and physics energy."""
from garmentgnn.metrics.garment_metrics import (METRIC_UNITS, collision_rate, curvature_error,
                                                edge_length_error, evaluate, evaluate_inputs,
                                                face_normal_error, physics_energy,
                                                vertex_distance, vertex_normal_error)

__all__ = ["METRIC_UNITS", "collision_rate", "curvature_error", "edge_length_error", "evaluate",
           "evaluate_inputs", "face_normal_error", "physics_energy", "vertex_distance",
           "vertex_normal_error"]
