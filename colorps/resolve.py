"""What a capture's settings mean for its files, resolved once before any matching.

Some settings are "auto" because their value depends on how each stack is
stored: the clip and dark levels on the pixel type and encoding of its files
(:func:`colorps.io.input_levels`), the noise model's quantisation on the same
(:func:`colorps.noise.file_noise`). A :class:`StackModel` says this for one
stack; :func:`resolve` combines the user's :class:`~colorps.Options` with the
scene's and the gauge's into one :class:`Resolved`, which
:func:`colorps.reconstruct` and every step after it read, and nothing resolves
again.

========================  ==================================================
stack                     :class:`StackModel`
========================  ==================================================
numpy arrays              :meth:`StackModel.floating`: nothing clipped,
                          dark below :data:`~colorps.options.FLOAT_DARK_LEVEL`,
                          no quantisation
image files               :meth:`StackModel.of_file`: from the first file's
                          header (a stack's files share one pixel type)
a rendered gauge          :meth:`StackModel.rendered`: nothing clipped, the
                          scene's dark level, no quantisation
========================  ==================================================

Levels the user gives (not "auto") apply to both stacks, but to a rendered
gauge, whose levels are fixed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from .noise import NoiseModel, file_noise
from .options import FLOAT_DARK_LEVEL, Options

__all__ = ["Resolved", "StackModel", "resolve"]


@dataclass(frozen=True)
class StackModel:
    """The levels and pixel noise one stack's storage implies.

    Attributes
    ----------
    clip_level : float or None
        Linear value from which a measurement counts as clipped (None: never).
    dark_level : float
        Linear value below which a measurement counts as too dark.
    noise : NoiseModel
        The storage's quantisation (read noise and gain 0 until given or
        fitted to the gauge).
    fixed : bool
        The levels hold whatever the options say (a rendered gauge).
    """

    clip_level: float | None
    dark_level: float
    noise: NoiseModel
    fixed: bool = False

    @classmethod
    def floating(cls) -> StackModel:
        """Floating-point arrays: nothing clipped, no quantisation."""
        return cls(None, FLOAT_DARK_LEVEL, NoiseModel(read=0.0, gain=0.0))

    @classmethod
    def of_file(cls, source, encoding: str = "auto") -> StackModel:
        """What a file's pixel type means, decoded with ``encoding``.

        ``source`` is the file or its :class:`~colorps.io.ImageInfo`."""
        from .io import input_levels

        return cls(*input_levels(source, encoding), file_noise(source, encoding))

    @classmethod
    def rendered(cls, dark_level: float) -> StackModel:
        """A gauge rendered in floating point: nothing clipped, whatever the
        options say, and the scene's ``dark_level``."""
        return cls(None, dark_level, NoiseModel(read=0.0, gain=0.0), fixed=True)

    def levels(self, options: Options) -> tuple[float | None, float]:
        """(clip, dark) of this stack under ``options``: "auto" fields from the
        storage, given ones as they are (unless :attr:`fixed`)."""
        if self.fixed:
            return self.clip_level, self.dark_level
        resolved = options.with_levels(self.clip_level, self.dark_level)
        return resolved.clip_level, resolved.dark_level


@dataclass(frozen=True)
class Resolved:
    """A capture's settings with every "auto" level resolved (see :func:`resolve`).

    Attributes
    ----------
    requested : Options
        The settings as given ("auto" levels kept: each stack resolves its own).
    scene, gauge : StackModel
    """

    requested: Options
    scene: StackModel
    gauge: StackModel

    @property
    def options(self) -> Options:
        """The settings with the scene's levels in place of "auto"."""
        return self.requested.with_levels(*self.scene.levels(self.requested))

    @property
    def gauge_levels(self) -> tuple[float | None, float]:
        """(clip, dark) levels of the gauge's measurements."""
        return self.gauge.levels(self.requested)

    def replace(self, **changes) -> Resolved:
        """A copy with fields of the requested :class:`Options` changed."""
        return dataclasses.replace(self, requested=self.requested.replace(**changes))


def resolve(options: Options | Resolved | None = None, *, scene: StackModel | None = None,
            gauge: StackModel | None = None, **changes) -> Resolved:
    """Resolve a capture's settings against what its stacks are.

    Parameters
    ----------
    options : Options or Resolved, optional
        The settings (default ``Options()``); a Resolved is taken as it is
        (``scene`` and ``gauge`` then replace its stacks when given).
    scene : StackModel, optional
        How the scene is stored (default :meth:`StackModel.floating`).
    gauge : StackModel, optional
        How the gauge is stored (default: as the scene).
    **changes
        Fields of :class:`Options` to change.

    Returns
    -------
    Resolved

    Examples
    --------
    >>> from colorps import Options
    >>> from colorps.resolve import StackModel, resolve
    >>> from colorps.noise import NoiseModel
    >>> eight_bit = StackModel(0.99, 0.0006, NoiseModel(0.0, 0.0, pixel_type="int"))
    >>> run = resolve(Options(dark_level=0.01), scene=eight_bit)
    >>> run.options.clip_level, run.options.dark_level, run.gauge_levels
    (0.99, 0.01, (0.99, 0.01))
    """
    if isinstance(options, Resolved):
        run = dataclasses.replace(options, scene=scene or options.scene,
                                  gauge=gauge or options.gauge)
        return run.replace(**changes) if changes else run
    scene = scene or StackModel.floating()
    return Resolved((options or Options()).replace(**changes), scene, gauge or scene)
