"""Trained methods on your own garment, body and motion (``garmentgnn predict``):
:func:`predict_garment_motion` and the files it writes (:func:`write_prediction`)."""
from garmentgnn.inference.output import output_paths, write_prediction
from garmentgnn.inference.predict import (LBS, Prediction, body_entry, load_method,
                                          predict_garment_motion, predict_sequence)

__all__ = ["LBS", "Prediction", "body_entry", "load_method", "output_paths",
           "predict_garment_motion", "predict_sequence", "write_prediction"]
