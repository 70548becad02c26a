"""Exact label rendering by ray casting (vectorised numpy, z-buffered).

Each pixel ``(u, v)`` is labelled by the first surface its ray through the pixel centre
hits: the ray is ``X(t) = t * d`` with ``d = ((u - cx) / fx, (v - cy) / fy, 1)``, so ``t`` is
the depth ``z`` (mm). Cylinders and spheres are intersected analytically (quadratics), so a
mask is the exact projection of the 3D model sampled at pixel centres: a cylinder's side
is bounded by its two analytic limb lines, its caps by ellipses. Rays are cast only inside
each primitive's projected bounding box (clipped to the image), which bounds the cost.
Nearer surfaces win over farther ones (z-buffer), also between instruments.

A distorted lens (``camera.distortion``, pinhole or fisheye; :mod:`mistool.lens`) is
rendered exactly too: pixel ``(u, v)``'s ray goes through its *undistorted* position, so
``d = (x, y, 1)`` with ``(x, y)`` the ideal normalised coordinates of the pixel centre
(computed once per camera, iteratively to < 1e-9 px). The masks then show the lens' bent
outlines while the 3D truth stays exact.

Boundary bias (``bias_px``, a segmentation that is uniformly too fat or too thin): every
primitive's radius is inflated (deflated when negative) per ray by ``bias_px`` times the
rate at which the ray's distance to the primitive grows per pixel of image displacement
(``depth / f`` times the obliquity of the closest-approach direction), so that each
outline (cylinder limb lines, cap ellipses, sphere circles) moves outward by ``bias_px``
pixels, sub-pixel exactly to first order, at whatever depth each part is.
(With a distorted lens, ``bias_px`` is in pixels of the ideal image: approximately the
image's pixels, exact at the principal point.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mistool.lens import distort_points, ideal_bounds, undistort_points
from mistool.synth.scene import Cylinder, ImageCamera, PartGeometry, Primitive, Sphere

#: Rays hitting nearer than this (mm) are ignored (the lens).
NEAR_MM = 1.0


@dataclass
class RenderBuffers:
    """The result of rendering one frame."""

    depth: np.ndarray
    """(H, W) float32 depth of the first hit (mm); ``inf`` where no hit."""
    instance: np.ndarray
    """(H, W) uint8: 0 background, ``i + 1`` for instrument ``i``."""
    part: np.ndarray
    """(H, W) uint8: 0 background, 1 shaft, 2 wrist, 3 clasper (3D parts)."""
    alone: list[np.ndarray]
    """Per instrument, its (H, W) uint8 part map rendered without the other instruments
    (what occlusion between instruments hid)."""


PART_CODES: dict[str, int] = {"shaft": 1, "wrist": 2, "clasper": 3}


class RayCaster:
    """Casts the rays of one camera; the normalised ray grid is computed once."""

    def __init__(self, cam: ImageCamera) -> None:
        self.cam = cam
        c = cam.camera
        self.xn = ((np.arange(cam.width, dtype=np.float64) - c.cx) / c.fx).astype(np.float32)
        self.yn = ((np.arange(cam.height, dtype=np.float64) - c.cy) / c.fy).astype(np.float32)
        # |d|^2 = xn^2 + yn^2 + 1, separable, so compute it per box from these two vectors
        self.xn2 = self.xn * self.xn
        self.yn2 = self.yn * self.yn + np.float32(1.0)
        self._lens: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        if c.distorted:  # per-pixel rays through the undistorted pixel centres
            u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
            ideal = undistort_points(np.stack([u.ravel(), v.ravel()], axis=1), c)
            xl = ((ideal[:, 0] - c.cx) / c.fx).reshape(cam.height, cam.width)
            yl = ((ideal[:, 1] - c.cy) / c.fy).reshape(cam.height, cam.width)
            self._lens = (
                xl.astype(np.float32),
                yl.astype(np.float32),
                (xl * xl + yl * yl + 1.0).astype(np.float32),
            )

    def _rays(self, box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Normalised ray components ``x``, ``y`` and ``|d|^2`` over a pixel box, as arrays
        that broadcast to (h, w) (separable for an ideal lens)."""
        x0, y0, x1, y1 = box
        if self._lens is not None:
            xl, yl, dl = self._lens
            return xl[y0:y1, x0:x1], yl[y0:y1, x0:x1], dl[y0:y1, x0:x1]
        dd = self.xn2[x0:x1][None, :] + self.yn2[y0:y1][:, None]
        return self.xn[x0:x1][None, :], self.yn[y0:y1][:, None], dd

    def _image_box(
        self, u0: float, v0: float, u1: float, v1: float
    ) -> tuple[float, float, float, float]:
        """The box of the camera's image covering the ideal-image box (u0, v0, u1, v1):
        its boundary, clipped to what the camera sees, distorted (the image of a box's
        inside lies inside the image of its boundary)."""
        c = self.cam.camera
        if not c.distorted:
            return u0, v0, u1, v1
        bx0, by0, bx1, by1 = ideal_bounds(c, (self.cam.width, self.cam.height))
        u0, v0 = max(u0, bx0 - 2.0), max(v0, by0 - 2.0)
        u1, v1 = min(u1, bx1 + 2.0), min(v1, by1 + 2.0)
        if u1 <= u0 or v1 <= v0:
            return 0.0, 0.0, -1.0, -1.0
        us, vs = np.linspace(u0, u1, 33), np.linspace(v0, v1, 33)
        edge = np.concatenate(
            [
                np.stack([us, np.full_like(us, v0)], 1),
                np.stack([us, np.full_like(us, v1)], 1),
                np.stack([np.full_like(vs, u0), vs], 1),
                np.stack([np.full_like(vs, u1), vs], 1),
            ]
        )
        img = distort_points(edge, c)
        lo, hi = img.min(axis=0) - 2.0, img.max(axis=0) + 2.0
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    # ----------------------------------------------------------------------------------
    def _bbox(
        self, centres: list[np.ndarray], radius: float, pad_px: float = 0.0
    ) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1), exclusive ends, bounding spheres of ``radius`` at the
        given centres and everything between them (their convex hull), grown by ``pad_px``;
        None if empty."""
        pts = np.array(centres, dtype=np.float64)
        if pts.shape[0] == 2:  # clip the segment to the near plane
            z = pts[:, 2]
            zmin = NEAR_MM + radius
            if (z < zmin).all():
                return None
            if (z < zmin).any():
                a, b = (pts[0], pts[1]) if z[0] < zmin else (pts[1], pts[0])
                s = (zmin - a[2]) / (b[2] - a[2])
                pts = np.array([a + s * (b - a), b])
        elif (pts[:, 2] < NEAR_MM + radius).all():
            return None
        c = self.cam.camera
        z = np.maximum(pts[:, 2] - radius, NEAR_MM)
        u = c.fx * pts[:, 0] / pts[:, 2] + c.cx
        v = c.fy * pts[:, 1] / pts[:, 2] + c.cy
        # a sphere of radius r at depth z projects inside a circle of radius about f r / (z - r)
        ru = c.fx * radius / z * 1.5 + 2.0 + pad_px
        rv = c.fy * radius / z * 1.5 + 2.0 + pad_px
        bu0, bv0, bu1, bv1 = self._image_box(
            float((u - ru).min()),
            float((v - rv).min()),
            float((u + ru).max()),
            float((v + rv).max()),
        )
        x0 = int(np.floor(max(bu0, 0)))
        x1 = int(np.ceil(min(bu1 + 1, self.cam.width)))
        y0 = int(np.floor(max(bv0, 0)))
        y1 = int(np.ceil(min(bv1 + 1, self.cam.height)))
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1, y1

    def _cylinder(
        self, cyl: Cylinder, bias_px: float = 0.0
    ) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
        p0 = np.asarray(cyl.p0, dtype=np.float64)
        a = np.asarray(cyl.axis, dtype=np.float64)
        box = self._bbox([p0, p0 + cyl.length * a], cyl.radius, abs(bias_px))
        if box is None:
            return None
        xn, yn, dd = self._rays(box)
        f32 = np.float32
        c = self.cam.camera
        ifx, ify = f32(1.0 / c.fx), f32(1.0 / c.fy)
        da = f32(a[0]) * xn + (f32(a[1]) * yn + f32(a[2]))  # d . a
        dp = f32(p0[0]) * xn + (f32(p0[1]) * yn + f32(p0[2]))  # d . p0
        pa = float(p0 @ a)
        # |t d - p0|_perp^2 = r^2  ->  A t^2 - 2 B t + C = 0
        aa = dd - da * da
        bb = dp - da * f32(pa)
        with np.errstate(invalid="ignore", divide="ignore"):
            if bias_px:
                # the ray's distance to the axis is smallest at t* = B / A (its depth),
                # along n = d x a / |d x a|; one pixel of image displacement changes it by
                # t* |(n_x / fx, n_y / fy)|
                nx = yn * f32(a[2]) - f32(a[1])
                ny = f32(a[0]) - xn * f32(a[2])
                grow = np.abs(bb / aa) * np.sqrt(
                    (nx * nx * ifx * ifx + ny * ny * ify * ify) / np.maximum(aa, f32(1e-12))
                )
                rad = np.maximum(f32(cyl.radius) + f32(bias_px) * grow, f32(0.0))
            else:
                rad = f32(cyl.radius)
            cc = f32(float(p0 @ p0) - pa * pa) - rad * rad
            disc = bb * bb - aa * cc
            hit = disc >= 0
            t = (bb - np.sqrt(np.maximum(disc, 0))) / aa
            s = t * da - f32(pa)  # axial coordinate
            t = np.where(hit & (s >= 0) & (s <= cyl.length), t, np.inf)
            # the one cap facing the camera (the camera is outside the cylinder)
            cap_s = None
            if -pa > cyl.length:
                cap_s = cyl.length
            elif -pa < 0:
                cap_s = 0.0
            if cap_s is not None:
                tc = f32(cap_s + pa) / da
                # squared distance from the axis at the cap: |t d - p0|^2 - cap_s^2
                rho2 = tc * tc * dd - f32(2.0) * tc * dp + f32(float(p0 @ p0) - cap_s**2)
                rad_c = f32(cyl.radius)
                if bias_px:
                    # the hit's in-plane offset w from the cap centre q; a pixel step moves
                    # the hit by t (dd_pix - (a . dd_pix) / (a . d) d), dd_pix = e_x / fx
                    q = p0 + cap_s * a
                    wx = tc * xn - f32(q[0])
                    wy = tc * yn - f32(q[1])
                    wz = tc - f32(q[2])
                    wn = np.sqrt(np.maximum(wx * wx + wy * wy + wz * wz, f32(1e-12)))
                    k = (wx * xn + wy * yn + wz) / (wn * da)  # (w^ . d) / (a . d)
                    gu = (wx / wn - f32(a[0]) * k) * ifx
                    gv = (wy / wn - f32(a[1]) * k) * ify
                    rad_c = np.maximum(
                        rad_c + f32(bias_px) * np.abs(tc) * np.sqrt(gu * gu + gv * gv), f32(0.0)
                    )
                tc = np.where((rho2 <= rad_c * rad_c) & (tc > 0), tc, np.inf)
                t = np.minimum(t, tc)
        t = np.where(t >= NEAR_MM, t, np.inf)
        return box, t

    def _sphere(
        self, sph: Sphere, bias_px: float = 0.0
    ) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
        c = np.asarray(sph.centre, dtype=np.float64)
        box = self._bbox([c], sph.radius, abs(bias_px))
        if box is None:
            return None
        xn, yn, dd = self._rays(box)
        f32 = np.float32
        dc = f32(c[0]) * xn + (f32(c[1]) * yn + f32(c[2]))
        with np.errstate(invalid="ignore", divide="ignore"):
            if bias_px:
                # closest approach t* = (d . c) / |d|^2, along n = t* d - c
                cam = self.cam.camera
                ts = dc / dd
                nx = ts * xn - f32(c[0])
                ny = ts * yn - f32(c[1])
                nz = ts - f32(c[2])
                nn = np.maximum(nx * nx + ny * ny + nz * nz, f32(1e-12))
                grow = np.abs(ts) * np.sqrt(
                    (nx * nx / f32(cam.fx**2) + ny * ny / f32(cam.fy**2)) / nn
                )
                rad = np.maximum(f32(sph.radius) + f32(bias_px) * grow, f32(0.0))
            else:
                rad = f32(sph.radius)
            disc = dc * dc - dd * (f32(float(c @ c)) - rad * rad)
            t = np.where(disc >= 0, (dc - np.sqrt(np.maximum(disc, 0))) / dd, np.inf)
        t = np.where(t >= NEAR_MM, t, np.inf)
        return box, t

    def depth_of(
        self, prim: Primitive, bias_px: float = 0.0
    ) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
        """Depth (mm, float32, inf where missed) of one primitive over its pixel box
        ``(x0, y0, x1, y1)``; None when it projects outside the image. ``bias_px`` moves
        its outline outward (inward if negative) by that many px (module docstring)."""
        if isinstance(prim, Cylinder):
            return self._cylinder(prim, bias_px)
        return self._sphere(prim, bias_px)

    def render(self, instruments: list[list[PartGeometry]], bias_px: float = 0.0) -> RenderBuffers:
        """Render instruments (each a list of parts) into depth, instance and part maps;
        each instrument is rendered alone, then composited by depth. ``bias_px``: every
        outline moved outward by that many px (inward if negative; see module docstring)."""
        h, w = self.cam.height, self.cam.width
        depth = np.full((h, w), np.inf, dtype=np.float32)
        instance = np.zeros((h, w), dtype=np.uint8)
        part = np.zeros((h, w), dtype=np.uint8)
        alone: list[np.ndarray] = []
        for i, parts in enumerate(instruments):
            d_i = np.full((h, w), np.inf, dtype=np.float32)
            p_i = np.zeros((h, w), dtype=np.uint8)
            for pg in parts:
                code = PART_CODES[pg.part]
                for prim in pg.primitives:
                    res = self.depth_of(prim, bias_px)
                    if res is None:
                        continue
                    (x0, y0, x1, y1), t = res
                    zb = d_i[y0:y1, x0:x1]
                    nearer = t < zb
                    zb[nearer] = t[nearer]
                    p_i[y0:y1, x0:x1][nearer] = code
            if i == 0:
                depth, part = d_i.copy(), p_i.copy()
                instance[p_i > 0] = 1
            else:
                nearer = d_i < depth
                depth[nearer] = d_i[nearer]
                instance[nearer] = i + 1
                part[nearer] = p_i[nearer]
            alone.append(p_i)
        return RenderBuffers(depth, instance, part, alone)
