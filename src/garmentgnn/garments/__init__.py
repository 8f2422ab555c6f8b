"""Garments: the rest-state :class:`Garment` (mesh + sewing-pattern / material UVs),
procedural templates sized from a body, and mesh file I/O."""
from garmentgnn.garments.garment import KINDS, Garment
from garmentgnn.garments.io import load_garment, save_garment
from garmentgnn.garments.templates import (FLARES, RESOLUTIONS, SKIRT_LENGTHS, SLEEVES,
                                           TEMPLATES, TROUSER_LENGTHS, dress, jumpsuit,
                                           make_garment, skirt, trousers, tshirt)

__all__ = ["Garment", "KINDS", "FLARES", "RESOLUTIONS", "SKIRT_LENGTHS", "SLEEVES",
           "TEMPLATES", "TROUSER_LENGTHS", "dress", "jumpsuit", "load_garment", "make_garment",
           "save_garment", "skirt", "trousers", "tshirt"]
