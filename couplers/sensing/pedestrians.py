"""SUMO pedestrians as moving features (the ``[features]`` config table).

With ``[features] pedestrians = true`` every SUMO person walking in the net is a feature of model (2)
of Brambilla et al.: a point x_F = [px, py, vx, vy] that vehicles measure with model (4), exactly as
the static landmarks of ``features.add.xml`` (same V2F path: range, and ``[perception]``'s field of
view, P_D and occlusion when present). Positions and velocities come from libsumo's person getters
(:func:`person_states`); the Sec. V studies' moving features are the controlled counterpart.

* Stable indices: the frame's ``truth.features_true`` / ``feature_ids`` hold the static features
  first (rows 0..K0-1, as without pedestrians), then every person in the order of first appearance
  (:class:`FeatureRegistry`): a person keeps its row for the whole run, so ``truth.v2f_feature``
  (the true association, and the track id of the known-association methods) is stable. A person
  that has left (arrived) keeps its row with NaN state; it is never measured again.
* Class: ``truth.feature_class`` (K,) and ``Frame.v2f_class`` (O,) int8, ``CLASS_STATIC`` (0) or
  ``CLASS_PEDESTRIAN`` (1) (couplers.sensing.perception); a false detection (clutter) is reported as static:
  the perception model draws it as a static object (relative velocity -v_vehicle), so a classifier
  would label it as what it looks like.
* Pedestrians do not occlude (they are thin and the sensors of the project see over them: a
  simplification, stated in docs/architecture.md); they are not V2V nodes and have no GNSS.

Cost: libsumo has no batch getter for persons; three plain getters per person and step
(``getPosition``, ``getSpeed``, ``getAngle``), as for the vehicles (couplers.traffic.sumo). Measured
on arterial_ped (about 65 persons walking): see docs/validation/realistic_sensing.md "SUMO pedestrians".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from coloc.core.vehicles import match_ids
from couplers.sensing.perception import CLASS_PEDESTRIAN, CLASS_STATIC

__all__ = ["FeaturesParams", "PersonStates", "person_states", "FeatureRegistry", "CLASS_STATIC",
           "CLASS_PEDESTRIAN"]


@dataclass(frozen=True)
class FeaturesParams:
    """The ``[features]`` table: which moving objects of SUMO are features besides the static POIs.

    ``pedestrians``: every SUMO person is a moving feature (the net folder must name a persons file,
    ``[files] persons``; SUMO scenarios only).
    """

    pedestrians: bool = False


@dataclass(frozen=True)
class PersonStates:
    """True states of the persons walking after one step."""

    ids: np.ndarray  # (P,) str
    xy: np.ndarray  # (P, 2) m
    velocity: np.ndarray  # (P, 2) m/s


def person_states(person) -> PersonStates:
    """Every person's position and velocity from libsumo's ``person`` domain (``libsumo.person``).

    Velocity: speed along the heading; SUMO's navigational angle (0 = north, clockwise) becomes a
    heading from +x, counter-clockwise, as for the vehicles."""
    ids = list(person.getIDList())
    p = len(ids)
    xy = np.array([person.getPosition(q) for q in ids], dtype=float).reshape(p, 2)
    speed = np.array([person.getSpeed(q) for q in ids], dtype=float)
    heading = np.radians(90.0 - np.array([person.getAngle(q) for q in ids], dtype=float))
    velocity = speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1).reshape(p, 2)
    return PersonStates(ids=np.array(ids, dtype=object), xy=xy, velocity=velocity)


class FeatureRegistry:
    """Stable rows of the features of a run: the K0 static ones, then persons by first appearance."""

    def __init__(self, static_ids: np.ndarray, static_states: np.ndarray):
        self.k0 = len(static_ids)
        self.ids = np.asarray(static_ids, dtype=object)
        self.states = np.asarray(static_states, dtype=float)
        self.klass = np.full(self.k0, CLASS_STATIC, dtype=np.int8)
        self._person_ids = np.empty(0, dtype=object)  # registered persons, in row order after k0

    def update(self, persons: PersonStates) -> np.ndarray:
        """Register new persons, write this step's states (NaN for persons gone); returns the (P,)
        registry row of each person of ``persons``."""
        idx = match_ids(self._person_ids, persons.ids)
        new = idx < 0
        if new.any():
            n_old = self._person_ids.size
            self._person_ids = np.concatenate([self._person_ids, persons.ids[new]])
            idx[new] = n_old + np.arange(int(new.sum()))
            self.ids = np.concatenate([self.ids, persons.ids[new]])
            self.klass = np.concatenate([self.klass, np.full(int(new.sum()), CLASS_PEDESTRIAN, dtype=np.int8)])
        states = np.full((self.k0 + self._person_ids.size, 4), np.nan)
        states[: self.k0] = self.states[: self.k0]
        rows = self.k0 + idx
        states[rows, :2] = persons.xy
        states[rows, 2:] = persons.velocity
        self.states = states
        return rows
