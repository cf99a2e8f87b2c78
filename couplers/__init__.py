"""couplers: simulation -> measurement frames.

Imports libsumo, sumolib, shapely and numpy; produces ``coloc.core.frame.Frame``
objects, the only thing that crosses into the estimators.
"""
