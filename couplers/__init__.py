"""couplers: simulation -> measurement frames.

Imports libsumo, sumolib, shapely and numpy; produces ``coloc.core.frame.Frame``
objects, the only thing that crosses into the estimators.

Rooms, by what they model (imports run one way, down this list; tests/couplers/test_couplers_layers.py):

* ``couplers.net``: the net folder and its import (net, routes, zones, areas, buildings, georef);
* ``couplers.traffic``: the traffic simulation (SUMO through libsumo);
* ``couplers.sensing``: the sensor models (GNSS error, inertial, perception, occlusion, V2X, RSUs);
* top level: the couplers proper, which combine traffic and sensing into frames
  (``sumo_coupler``, ``scenarios``, ``frohle_scenario``), and ``errors`` / ``publish``, used by every room.
"""
