"""The normals' uncertainty from a fitted falloff's trade with their tilt.

A finish fitted to a scene's own images (``--lights``, or the finish route of a
gauge of another finish than the scene's) fits its diffuse falloff g and the
scene's normals together, and the two trade: normals tilted a little, with a
falloff a little brighter towards grazing light, explain the images about as
well as the true ones. A glossy sphere path-traced by Mitsuba 3, solved from its
own images under its true lights, fitted g = 1.27 at grazing incidence and came
out 1.3 degrees off everywhere, its radii (the noise's and the misfit's: 0.05
degrees) holding 2 % of its errors; with the falloff fitted at its true normals
(never brighter towards grazing) it came out 0.07 degrees off.

Where a fitted falloff rises towards grazing by more than TRADE_TOLERANCE, the
gauge rendered with it is matched against one rendered with the nearest falloff
that does not (:meth:`colorps.brdf.BRDF.never_brighter_towards_grazing`): the
angle between each of its normals and the normal so matched is how far that
rise moves a normal. Whether the rise is the finish's or the fit's, the normal is
off by between 0 and that angle, in one direction: it is added to the 68 %
radius of every scene pixel solved at that normal (a bias's bound, not in
quadrature as a scatter would be).
"""

from __future__ import annotations

import numpy as np

from .brdf import BRDF
from .geometry import angular_error, at_nearest_normal
from .lights import Lights
from .reconstruct import reconstruct
from .results import Reconstruction
from .virtual import rendered

__all__ = ["TRADE_TOLERANCE", "falloff_trade", "with_falloff_trade"]

#: A fitted falloff within this of one never brighter towards grazing (at every
#: knot, relative to 1 at normal incidence) trades nothing worth a radius.
TRADE_TOLERANCE = 0.01


def falloff_trade(lights: Lights, brdf: BRDF, radius: float, bands: int
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """How far (degrees) the rise of ``brdf``'s falloff towards grazing moves
    each normal of a virtual gauge under ``lights``.

    Parameters
    ----------
    lights : Lights
        The lights the scene was solved under.
    brdf : BRDF
        The finish fitted to it.
    radius : float
        Radius (pixels) of the virtual gauges rendered.
    bands : int
        The scene's bands.

    Returns
    -------
    (normals, angles) or None
        The (P, 3) normals of the gauge rendered with ``brdf`` and, at each, the
        angle to the normal matched on the gauge rendered with
        :meth:`~colorps.brdf.BRDF.never_brighter_towards_grazing`; None when the
        falloff rises by no more than TRADE_TOLERANCE.
    """
    steady = brdf.never_brighter_towards_grazing()
    if np.max(np.abs(np.subtract(brdf.falloff, steady.falloff))) <= TRADE_TOLERANCE:
        return None
    fitted, flat = (rendered(lights, finish, radius, bands) for finish in (brdf, steady))
    matched = reconstruct(fitted.stack, flat.stack, flat, mask=fitted.mask)
    both = fitted.mask & matched.solved
    return fitted.normals[both], angular_error(matched.normals[both], fitted.normals[both])


def with_falloff_trade(result: Reconstruction, finish, lights: Lights | None, radius: float,
                       record: dict | None) -> Reconstruction:
    """``result`` with :func:`falloff_trade` added to its 68 % radii (as a bias)
    when it was
    solved with a fitted finish (``finish``: (BRDF, its fits), None for the
    gauge's own) whose falloff rises towards grazing; ``record`` (the run's
    gauge or lights check) then gets ``falloff_trade``: the falloff without the
    rise and the median angle added over the solved pixels (degrees)."""
    if finish is None or lights is None:
        return result
    trade = falloff_trade(lights, finish[0], radius, result.albedo.shape[-1])
    if trade is None:
        return result
    added = at_nearest_normal(*trade, result.normals)
    if record is not None:
        record["falloff_trade"] = dict(
            falloff=list(finish[0].never_brighter_towards_grazing().falloff),
            normals_off_deg=float(np.nanmedian(added[result.solved])))
    return result.with_uncertainty_added(added, bias=True)
