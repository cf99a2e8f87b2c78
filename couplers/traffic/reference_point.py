"""The point of a vehicle the SUMO world reports ([scenario] reference_point): pure, without libsumo (the config
validates the key with it)."""

from __future__ import annotations

import numpy as np

# The point of a vehicle that the world reports (its position in the frames, the truth, every sensor):
# "front_bumper", SUMO's vehicle.getPosition (the centre of the front bumper; SUMO documentation, TraCI
# "Vehicle Value Retrieval", position), or "centre", the middle of the body axis, half the vehicle's length
# behind the bumper along SUMO's angle (the chord from the rear to the front bumper, both on the lane path).
# The velocity is speed x body direction either way: the chord midpoint's velocity to second order, while the
# bumper slides sideways at about length / 2 x yaw rate in a turn (docs/validation/consistency.md
# "Kinematics of the world").
REFERENCE_POINTS = ("front_bumper", "centre")


def centre_from_front(front: np.ndarray, direction: np.ndarray, half_length: np.ndarray) -> np.ndarray:
    """(N, 2) centres of vehicles whose front bumpers are at ``front`` (N, 2): half their length
    ``half_length`` (N,) back along the unit body directions ``direction`` (N, 2)."""
    return front - half_length[:, None] * direction
