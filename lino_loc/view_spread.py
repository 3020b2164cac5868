"""Which pan a standing robot should look at next once its belief is gathered: the one
farthest from every view taken.

Once the filter has found the neighbourhood, the standing match (:mod:`lino_loc.standing_match`)
places the robot from all the views taken since the base stopped, and its error is most of
what is left of the position's uncertainty. The paper's H(u) (section 4) cannot see that
error: it judges the particles with the nearest-neighbour model, whose kernels are 35 cm wide,
so once the belief is gathered every pan looks alike to it. Views that overlap see the same
surfaces, so what misleads the match in one (the map's interpolation between its lattice
poses, an object the survey did not have) misleads it in the other; views far apart err
apart, and their errors cancel in the joint match. So the next view is the candidate pan whose
camera direction is farthest from those of the views taken,

    s(u) = min_i |wrap(u - u_i)|   (rad, in [0, pi]),

a greedy max-min design of directions. With the per-pan reliability
(:mod:`lino_loc.pan_reliability`) a spoiled pan counts for ``r(u) s(u)``: the separation a
view brings when it is not spoiled.

The values are returned as :class:`lino_loc.active_vision.ActionValues` so that the policy
chooses, discounts and stops as it does with H(u): ``expected_entropy = -s(u)`` and
``current_entropy = 0``, so the "gain" of a pan is its separation (rad), and
``min_entropy_gain`` stops looking when every candidate is that close to a view taken.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lino_loc.active_vision import ActionValues
from lino_loc.poses import wrap_angle

FloatArray = NDArray[np.float64]


def separation(taken: ArrayLike, actions: ArrayLike) -> FloatArray:
    """``s(u)`` (A,): the angle (rad) from each pan of ``actions`` to the nearest of ``taken``
    (wrapped; pi for every pan when nothing was taken)."""
    u = np.asarray(actions, dtype=np.float64).reshape(-1)
    t = np.asarray(taken, dtype=np.float64).reshape(-1)
    if t.size == 0:
        return np.full(u.shape, np.pi)
    return np.abs(wrap_angle(u[:, None] - t[None, :])).min(axis=1)


def spread_values(taken: ArrayLike, actions: ArrayLike, n_particles: int = 0) -> ActionValues:
    """The spread rule's action values (module docstring) for the views taken at ``taken``."""
    u = np.asarray(actions, dtype=np.float64).reshape(-1)
    return ActionValues(actions=u, expected_entropy=-separation(taken, u), current_entropy=0.0,
                        n_particles=n_particles)
