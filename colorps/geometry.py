"""Normals: the sphere's normal field and the angle between two normal maps.

Conventions: pixel (x, y) = (column, row), pixel centres at integers; camera
space x right, y up, z towards the camera; orthographic view unless a
:class:`~colorps.camera.Camera` is given.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera

__all__ = ["angular_error", "at_nearest_normal", "circle_of_cone", "silhouette_cone",
           "sphere_normals"]

#: Newton steps fitting a sphere's cone to its silhouette circle (converges in 3-4).
CONE_NEWTON_STEPS = 8


def sphere_normals(shape: tuple[int, int], cx: float, cy: float, radius: float,
                   camera: Camera | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a sphere's image, and how far each pixel is towards its rim.

    Parameters
    ----------
    shape : (H, W)
        Image size in pixels.
    cx, cy, radius : float
        Silhouette centre and radius, pixels.
    camera : Camera, optional
        A pinhole camera (default: orthographic view). Off the optical axis a
        sphere's silhouette is an ellipse, elongated towards the principal
        point; the circle (cx, cy, radius) is taken to share its nearest and
        farthest points from the principal point, which fixes the sphere's
        direction and angular radius (a circle fitted to the ellipse does, to
        a fraction of a pixel).

    Returns
    -------
    normals : (H, W, 3) ndarray of float64
        Orthographic: n = ((x - cx) / r, -(y - cy) / r, sqrt(1 - nx^2 - ny^2)).
        Pinhole: the unit normal where the pixel's ray meets the sphere.
        nz is 0 outside the sphere's image (where the normal is meaningless).
    rho : (H, W) ndarray of float64
        The sine of the angle between the normal and the direction to the
        camera: 1 on the silhouette (orthographic: the distance from the centre
        in radii), above 1 outside.

    Examples
    --------
    >>> from colorps.geometry import sphere_normals
    >>> n, rho = sphere_normals((5, 5), 2, 2, 2)
    >>> n[2, 2].tolist(), n[0, 2].tolist(), float(rho[2, 0])
    ([0.0, -0.0, 1.0], [0.0, 1.0, 0.0], 1.0)
    """
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    if camera is not None:
        return _pinhole_sphere_normals(x, y, cx, cy, radius, camera, shape)
    nx = (x - cx) / radius
    ny = -(y - cy) / radius
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, None))
    return np.stack([nx, ny, nz], axis=-1), np.hypot(nx, ny)


def angular_error(a, b) -> np.ndarray:
    """Angle between normals, in degrees.

    Computed as atan2(|a x b|, a . b), which keeps its precision at small
    angles: arccos of the dot product cannot tell apart angles under about
    0.03 degrees between float32 unit vectors (two identical normals of a map
    came out up to 0.026 degrees apart), a floor under the medians of clean
    renders.

    Parameters
    ----------
    a, b : (..., 3) array_like
        Directions (broadcast against each other); unit vectors, or of any
        non-zero length.

    Returns
    -------
    (...) ndarray of float64
        Degrees in [0, 180]; NaN where either input is NaN.

    Examples
    --------
    >>> from colorps.geometry import angular_error
    >>> float(angular_error([1, 0, 0], [0, 0, 1]))
    90.0
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    sine = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.degrees(np.arctan2(sine, (a * b).sum(axis=-1)))


def at_nearest_normal(table_normals: np.ndarray, values: np.ndarray,
                      normals: np.ndarray) -> np.ndarray:
    """Each of ``normals`` (..., 3; NaN where unknown) given the value of the
    nearest of ``table_normals`` (P, 3) in ``values`` (P,): a quantity measured
    on a gauge's normals, looked up for a scene's (NaN where unknown)."""
    from scipy.spatial import cKDTree

    flat = np.asarray(normals, np.float64).reshape(-1, 3)
    out = np.full(flat.shape[0], np.nan)
    known = np.isfinite(flat).all(axis=1)
    out[known] = np.asarray(values)[cKDTree(table_normals).query(flat[known])[1]]
    return out.reshape(np.shape(normals)[:-1])


def _pinhole_sphere_normals(x, y, cx, cy, radius, camera: Camera, shape):
    """sphere_normals at pixel coordinates (x, y) of an image of ``shape`` under a
    pinhole camera.

    The cone of rays tangent to the sphere (axis at theta_c from the optical
    axis, half-angle alpha: :func:`_cone_of_circle`) gives the sphere's centre
    direction and, at unit distance, its radius sin(alpha). Each pixel's ray is
    then intersected with it.
    """
    px, py = camera.principal(shape)
    focal = camera.focal
    offset = np.array([(cx - px) * focal / camera.fx, (cy - py) * focal / camera.fy])
    distance = float(np.hypot(*offset))
    theta_c, alpha = _cone_of_circle(distance / focal, radius / focal)
    radial = offset / distance if distance > 0 else np.array([1.0, 0.0])
    # The axis in camera space: image x right, y down -> camera y up, looking along -z.
    centre = np.array([np.sin(theta_c) * radial[0], -np.sin(theta_c) * radial[1],
                       -np.cos(theta_c)])
    sphere_radius = np.sin(alpha)  # the centre at distance 1
    d = camera.rays(x, y, shape)
    along = d @ centre  # d . C, |C| = 1
    disc = along * along - (1.0 - sphere_radius ** 2)
    t = along - np.sqrt(np.clip(disc, 0.0, None))
    normals = (t[..., None] * d - centre) / sphere_radius
    facing = np.clip(-(normals * d).sum(axis=-1), 0.0, 1.0)
    rho = np.where(disc >= 0, np.sqrt(1.0 - facing * facing),
                   1.0 + np.sqrt(np.clip(-disc, 0.0, None)))
    normals[disc < 0] = 0.0
    return normals, rho


def _ellipse_of_cone(theta: float, alpha: float) -> tuple[float, float, float]:
    """(e, a, b) of the image ellipse (unit focal length) of a cone of half-angle
    alpha whose axis is theta off the optical axis (see :func:`_cone_of_circle`)."""
    k = np.cos(theta) ** 2 - np.sin(alpha) ** 2
    return (np.sin(theta) * np.cos(theta) / k, np.sin(alpha) * np.cos(alpha) / k,
            np.sin(alpha) / np.sqrt(k))


def silhouette_cone(rays: np.ndarray) -> tuple[np.ndarray, float]:
    """The cone of rays tangent to a sphere, fitted to rays through its edge.

    A ray d through the silhouette makes the cone's half-angle alpha with its
    axis u: d . u = cos(alpha), i.e. d . v = 1 for v = u / cos(alpha), which is
    linear in v: fitted by least squares.

    Parameters
    ----------
    rays : (N, 3) ndarray
        Unit rays (:meth:`colorps.camera.Camera.rays`) through edge points, N >= 3.

    Returns
    -------
    axis : (3,) ndarray
        Unit direction of the sphere's centre (camera space, z < 0 in front).
    alpha : float
        The cone's half-angle, radians.
    """
    v = np.linalg.lstsq(np.asarray(rays, dtype=np.float64), np.ones(len(rays)), rcond=None)[0]
    norm = float(np.linalg.norm(v))
    return v / norm, float(np.arccos(min(1.0, 1.0 / norm)))


def circle_of_cone(axis: np.ndarray, alpha: float, camera: Camera,
                   shape: tuple[int, int]) -> tuple[float, float, float]:
    """The circle (cx, cy, r) that stands for a sphere's cone in
    :func:`sphere_normals` (the one fitted to its image ellipse: the ellipse's
    centre, the mean of its semi-axes), in pixels of an image of ``shape``."""
    px, py = camera.principal(shape)
    focal = camera.focal
    theta = float(np.arccos(np.clip(-axis[2], -1.0, 1.0)))
    e, a, b = _ellipse_of_cone(theta, alpha)
    sideways = np.hypot(axis[0], axis[1])
    radial = np.array([axis[0], -axis[1]]) / sideways if sideways > 0 else np.zeros(2)
    offset = radial * e * focal
    return (float(px + offset[0] * camera.fx / focal), float(py + offset[1] * camera.fy / focal),
            float((a + b) / 2.0 * focal))


def _cone_of_circle(distance: float, radius: float) -> tuple[float, float]:
    """(theta_c, alpha) of the cone whose image ellipse a circle stands for.

    A cone of half-angle alpha whose axis is theta_c off the optical axis meets
    the image plane (at unit focal length) in an ellipse of centre distance e,
    semi-axes a (radial) and b ::

        k = cos^2 theta_c - sin^2 alpha
        e = sin theta_c cos theta_c / k,  a = sin alpha cos alpha / k,
        b = sin alpha / sqrt(k)

    The circle (``distance`` of its centre from the principal point,
    ``radius``, both over the focal length) is taken as the one fitted to it:
    e = distance, (a + b) / 2 = radius; solved by Newton's method from the
    cone through the circle's nearest and farthest points.
    """
    near, far = np.arctan(distance - radius), np.arctan(distance + radius)
    x = np.array([(near + far) / 2.0, (far - near) / 2.0])

    def misfit(v):
        e, a, b = _ellipse_of_cone(*v)
        return np.array([e - distance, (a + b) / 2.0 - radius])

    for _ in range(CONE_NEWTON_STEPS):
        f = misfit(x)
        h = 1e-7
        jacobian = np.column_stack([(misfit(x + np.array([h, 0.0])) - f) / h,
                                    (misfit(x + np.array([0.0, h])) - f) / h])
        try:
            x = x - np.linalg.solve(jacobian, f)
        except np.linalg.LinAlgError:
            break
    return float(x[0]), float(x[1])
