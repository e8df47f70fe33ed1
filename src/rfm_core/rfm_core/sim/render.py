"""RGB-D rendering of a Room by vectorised ray casting.

Every pixel casts a ray from the camera center through the pixel center (OpenCV/ROS
convention: pixel (u, v) is centred at integer coordinates). Rays are intersected with the
room's walls, floor and ceiling (the ray leaving the room box) and with every object box
(slab test in the box's frame, only for pixels inside the box's projected bounding
rectangle). The nearest hit gives depth (z in the camera optical frame), the instance id and
the surface point, which is shaded Lambertian with a texture fixed in object coordinates.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.geometry import BOX_EDGES, box_corners, convex_hull_area
from rfm_core.observations import CameraIntrinsics
from rfm_core.sim.furniture import world_parts
from rfm_core.sim.room import Material, Room

__all__ = ['RenderOutput', 'Renderer', 'NoiseModel']

_NEAR = 0.05                                  # m: rays start this far in front of the camera
_LIGHT = np.array([0.35, 0.55, 1.0]) / np.linalg.norm([0.35, 0.55, 1.0])  # to the light, map frame
_AMBIENT, _DIFFUSE = 0.5, 0.5


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise of a structured-light / stereo RGB-D camera.

    Depth is measured as a disparity ``d = f b / z`` of a reference sensor (focal ``f`` px,
    baseline ``b`` m), perturbed by spatially correlated noise (blocks of
    ``depth_noise_block_px`` pixels, as block matching produces) and quantised to
    1 / ``disparity_subpixel`` px: the depth error and the depth steps grow with z^2
    (about 1 cm noise and 2.6 cm steps at 3 m with the defaults). Holes appear at random and
    along depth discontinuities; depth beyond ``max_depth_m`` reads as missing.
    """

    color_sigma: float = 2.0            #: std of additive colour noise (8-bit levels)
    depth_focal_px: float = 580.0       #: reference sensor focal length (px)
    depth_baseline_m: float = 0.075     #: reference sensor baseline (m)
    disparity_sigma_px: float = 0.05    #: disparity noise std (px)
    disparity_subpixel: int = 8         #: disparity quantisation steps per pixel (0: none)
    depth_noise_block_px: int = 4       #: correlation length of the depth noise (px)
    depth_hole_fraction: float = 0.005  #: random missing depth pixels
    depth_edge_hole_fraction: float = 0.3   #: missing depth at discontinuities > 10 cm
    max_depth_m: float = 8.0            #: farther depth reads as missing
    # an active-stereo camera's artefacts (all off by default; see :meth:`realsense`)
    projector_baseline_m: float = 0.0   #: projector-to-camera baseline: an invalid band beside each
                                        #: depth edge, on the background, as wide as the parallax
    flying_pixel_fraction: float = 0.0  #: pixels at depth edges reading a depth between the two sides
    dark_dropout_below: float = 0.0     #: depth is lost on surfaces darker than this (luma, 0-1) ...
    dark_dropout_prob: float = 0.0      #: ... with this probability per pixel
    registration_offset_px: int = 0     #: depth registered to colour up to this many px off (per capture)
    exposure_drift: float = 0.0         #: auto-exposure: std of the per-frame step of log gain
    depth_delay_ms: tuple = (0.0, 0.0)  #: depth stamped this much after colour (uniform per frame)
    imu_gyro_bias_dps: float = 0.0      #: constant gyroscope bias (deg/s, random direction)
    imu_accel_bias: float = 0.0         #: constant accelerometer bias (m/s^2, random direction)
    imu_time_offset_ms: float = 0.0     #: IMU stamps this much late relative to the camera's
    odom_scale_error: float = 0.02      #: a robot's wheel odometry: std of its distance scale error ...
    odom_turn_error: float = 0.02       #: ... of its turn scale error (both drawn once per capture) ...
    odom_yaw_bias_dps: float = 0.5      #: ... and its constant yaw drift (deg/s, either sign)

    #: fields added after the first bags were written: left out of a stored config at defaults
    ARTEFACTS = ('projector_baseline_m', 'flying_pixel_fraction', 'dark_dropout_below', 'dark_dropout_prob',
                 'registration_offset_px', 'exposure_drift', 'depth_delay_ms', 'imu_gyro_bias_dps',
                 'imu_accel_bias', 'imu_time_offset_ms', 'odom_scale_error', 'odom_turn_error', 'odom_yaw_bias_dps')

    def __post_init__(self):
        object.__setattr__(self, 'depth_delay_ms', tuple(float(v) for v in self.depth_delay_ms))

    @classmethod
    def realsense(cls) -> 'NoiseModel':
        """An active-stereo RGB-D camera (RealSense D4xx-like): depth noise about 1 cm at 2 m and
        4 cm at 4 m (growing with range^2), coarser quantisation, projector shadows and flying
        pixels at depth edges, depth lost on dark surfaces, depth one pixel off colour,
        auto-exposure drift and stronger colour noise, depth stamped 3-10 ms after colour, an
        IMU with bias and a few ms of time offset."""
        return cls(color_sigma=4.0, depth_focal_px=380.0, depth_baseline_m=0.05, disparity_sigma_px=0.048,
                   disparity_subpixel=16, depth_noise_block_px=3, depth_hole_fraction=0.01,
                   depth_edge_hole_fraction=0.5, max_depth_m=6.0, projector_baseline_m=0.025,
                   flying_pixel_fraction=0.3, dark_dropout_below=0.12, dark_dropout_prob=0.7,
                   registration_offset_px=1, exposure_drift=0.03, depth_delay_ms=(3.0, 10.0),
                   imu_gyro_bias_dps=0.3, imu_accel_bias=0.05, imu_time_offset_ms=4.0)

    @classmethod
    def none(cls) -> 'NoiseModel':
        """No noise, no quantisation, no holes."""
        return cls(color_sigma=0.0, disparity_sigma_px=0.0, disparity_subpixel=0,
                   depth_hole_fraction=0.0, depth_edge_hole_fraction=0.0, max_depth_m=np.inf,
                   odom_scale_error=0.0, odom_turn_error=0.0, odom_yaw_bias_dps=0.0)


@dataclass
class RenderOutput:
    rgb: np.ndarray            #: (H, W, 3) uint8
    depth: np.ndarray          #: (H, W) float32, z in m, NaN where missing (noisy)
    depth_true: np.ndarray     #: (H, W) float32, exact z in m
    instance: np.ndarray       #: (H, W) int32: 0 room structure, k + 1 object k
    visible_pixels: np.ndarray     #: (N,) visible pixels per object
    unoccluded_pixels: np.ndarray  #: (N,) pixels per object in the image ignoring occlusion
    amodal_area: np.ndarray        #: (N,) area (px) of the full projection, in or out of image
    boxes_2d: np.ndarray           #: (N, 4) amodal 2D boxes clipped to the image


def _hash_noise(cells: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice cells (..., 2)."""
    x = cells[..., 0].astype(np.int64) * 73856093 ^ cells[..., 1].astype(np.int64) * 19349663
    x = (x ^ (seed * 83492791)) & 0xFFFFFFFF
    x = (x ^ (x >> 13)) * 1274126177 & 0xFFFFFFFF
    x = x ^ (x >> 16)
    return (x & 0xFFFF).astype(np.float32) / 65536.0


def _value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1) at continuous coordinates (bilinear between cells)."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = (u - iu).astype(np.float32), (v - iv).astype(np.float32)
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    corners = [_hash_noise(np.stack([iu + du, iv + dv], -1), seed) for du in (0, 1) for dv in (0, 1)]
    return ((corners[0] * (1 - fv) + corners[1] * fv) * (1 - fu)
            + (corners[2] * (1 - fv) + corners[3] * fv) * fu)


_TILE = 256       # texture tiles are _TILE x _TILE texels, repeating


def _texture_tile(material: Material):
    """(tile (T, T, 3) float32, texel size in m): the material's albedo on a repeating tile."""
    res = material.scale_m / 8.0
    grid = (np.arange(_TILE, dtype=np.float64) + 0.5) * res
    u, v = np.meshgrid(grid, grid)
    return _albedo(material, u.ravel(), v.ravel()).reshape(_TILE, _TILE, 3).astype(np.float32), res


def _albedo(material: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Albedo (P, 3) at surface coordinates u, v (m) of a surface with ``material``."""
    base = np.asarray(material.color, dtype=np.float32)
    if material.texture == 'plain' or material.contrast <= 0:
        return np.broadcast_to(base, (len(u), 3))
    s = material.scale_m
    if material.texture == 'wood':
        grain = _value_noise(u / (8 * s), v / s, material.seed)
        pattern = 0.5 + 0.5 * np.sin((v / s + 3 * grain) * np.pi)
    elif material.texture == 'fabric':
        pattern = 0.5 * (_value_noise(u / s, v / s, material.seed)
                         + (np.floor(u / (0.25 * s)) + np.floor(v / (0.25 * s))) % 2)
    elif material.texture == 'checker':
        pattern = (np.floor(u / s) + np.floor(v / s)) % 2
        pattern = 0.7 * pattern + 0.3 * _value_noise(u / (0.5 * s), v / (0.5 * s), material.seed)
    else:  # noise
        pattern = 0.6 * _value_noise(u / s, v / s, material.seed) + 0.4 * _value_noise(
            u / (0.3 * s), v / (0.3 * s), material.seed + 1)
    factor = 1.0 + material.contrast * (pattern.astype(np.float32) - 0.5) * 2.0
    return np.clip(base[None, :] * factor[:, None], 0.0, 1.0)


class Renderer:
    """Renders a Room from camera poses with fixed intrinsics."""

    def __init__(self, room: Room, intrinsics: CameraIntrinsics, noise: NoiseModel | None = None,
                 cull: bool = True):
        """``cull``: test each box only on the pixels of its projected bounding rectangle
        (False tests every pixel against every box: same images, for benchmarking)."""
        self.room = room
        self.cull = cull
        self.intrinsics = intrinsics
        self.noise = NoiseModel() if noise is None else noise
        w, h = intrinsics.width, intrinsics.height
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        # Ray directions with z = 1 in the camera frame: the ray parameter is the z depth.
        self._rays_cam = np.stack([(u - intrinsics.cx) / intrinsics.fx,
                                   (v - intrinsics.cy) / intrinsics.fy,
                                   np.ones_like(u)], -1).astype(np.float32)
        self._boxes = room.boxes
        self._corners = box_corners(self._boxes) if len(self._boxes) else np.zeros((0, 8, 3))
        # What rays hit: primitives (boxes), each an object's part (or its whole box) or a
        # piece of clutter (owner -1: in no ground truth), with the texture tile it wears.
        n = len(room.objects)
        prims, owner, tile = [], [], []
        for k, obj in enumerate(room.objects):
            parts = obj.box[None] if obj.parts is None else world_parts(obj.box, obj.parts)
            prims += list(parts)
            owner += [k] * len(parts)
            tile += [6 + k] * len(parts)
        for j, piece in enumerate(room.clutter):
            prims.append(piece.box)
            owner.append(-1)
            tile.append(6 + n + j)
        self._prims = np.array(prims, dtype=np.float64).reshape(-1, 7)
        self._prim_owner = np.array(owner, dtype=np.int64)
        self._prim_tile = np.array(tile, dtype=np.int64)
        self._clutter_corners = (box_corners(self._prims[self._prim_owner < 0]) if room.clutter
                                 else np.zeros((0, 8, 3)))
        # Texture tiles of the 6 room surfaces, the objects, then the clutter, as 8-bit albedo.
        tiles = ([_texture_tile(m) for m in room.walls] + [_texture_tile(o.material) for o in room.objects]
                 + [_texture_tile(c.material) for c in room.clutter])
        self._tiles = np.stack([np.rint(t * 255).astype(np.uint8) for t, _ in tiles])
        self._tile_scale = np.array([1.0 / res for _, res in tiles], dtype=np.float32)
        self._box_table = np.concatenate([np.zeros((1, 7)), self._prims]).astype(np.float32)
        # pixel labels: 0 room structure, i + 1 primitive i; instance = its owner + 1 (0: none)
        self._instance_of = np.concatenate([[0], np.where(self._prim_owner >= 0, self._prim_owner + 1, 0)])

    # ---------------------------------------------------------------- projection

    def _uv(self, cam: np.ndarray) -> np.ndarray:
        intr = self.intrinsics
        return np.stack([intr.fx * cam[..., 0] / cam[..., 2] + intr.cx,
                         intr.fy * cam[..., 1] / cam[..., 2] + intr.cy], -1)

    def _project_boxes(self, rot_wc: np.ndarray, pos: np.ndarray, corners: np.ndarray | None = None):
        """Per object: amodal projected area (px), clipped amodal 2D box, the pixel
        rectangle (u0, v0, u1, v1) that can contain it (u1 <= u0 when not in the image),
        and whether the projection lies entirely inside the image.

        The projection of a box is the convex hull of its projected corners; a box crossing
        the near plane is clipped there first (its edges are cut at z = near). The hull area
        is computed only for truncated boxes: for the others the caller counts pixels.
        """
        intr = self.intrinsics
        corners = self._corners if corners is None else corners
        n = len(corners)
        cam = (corners - pos) @ rot_wc                        # (N, 8, 3) camera frame
        in_front = cam[..., 2] > _NEAR
        area = np.zeros(n)
        lo = np.full((n, 2), np.inf)
        hi = np.full((n, 2), -np.inf)
        full = np.all(in_front, axis=1)
        if np.any(full):
            uv = self._uv(cam[full])
            lo[full], hi[full] = uv.min(1), uv.max(1)
        inside = (full & np.all(lo >= -0.5, axis=1) & (hi[:, 0] <= intr.width - 0.5)
                  & (hi[:, 1] <= intr.height - 0.5))
        truncated = full & ~inside
        if np.any(truncated):
            area[truncated] = convex_hull_area(self._uv(cam[truncated]))
        for k in np.flatnonzero(~full & np.any(in_front, axis=1)):
            a, b = cam[k, BOX_EDGES[:, 0]], cam[k, BOX_EDGES[:, 1]]
            crosses = (a[:, 2] > _NEAR) != (b[:, 2] > _NEAR)
            t = (_NEAR - a[crosses, 2]) / (b[crosses, 2] - a[crosses, 2])
            pts = np.concatenate([cam[k, in_front[k]],
                                  a[crosses] + t[:, None] * (b[crosses] - a[crosses])])
            uv = self._uv(pts)
            area[k] = convex_hull_area(uv[None])[0]
            lo[k], hi[k] = uv.min(0), uv.max(0)
        boxes_2d = np.stack([np.maximum(lo[:, 0], -0.5), np.maximum(lo[:, 1], -0.5),
                             np.minimum(hi[:, 0], intr.width - 0.5),
                             np.minimum(hi[:, 1], intr.height - 0.5)], -1)
        boxes_2d[~np.isfinite(boxes_2d)] = 0.0
        with np.errstate(invalid='ignore'):
            rect = np.stack([np.floor(lo[:, 0]), np.floor(lo[:, 1]),
                             np.ceil(hi[:, 0]) + 1, np.ceil(hi[:, 1]) + 1], -1)
        rect = np.nan_to_num(rect, nan=0.0, posinf=0.0, neginf=0.0)
        rect[:, [0, 2]] = np.clip(rect[:, [0, 2]], 0, intr.width)
        rect[:, [1, 3]] = np.clip(rect[:, [1, 3]], 0, intr.height)
        return area, boxes_2d, rect.astype(np.int64), inside

    # ---------------------------------------------------------------- rendering

    def render(self, rot_wc: np.ndarray, position: np.ndarray,
               rng: np.random.Generator | None = None) -> RenderOutput:
        """Render from a camera with orientation ``rot_wc`` (camera-to-map) at ``position``."""
        intr = self.intrinsics
        h, w = intr.height, intr.width
        rot_wc = np.asarray(rot_wc, dtype=np.float64)
        pos = np.asarray(position, dtype=np.float64)
        rays = (self._rays_cam @ rot_wc.T.astype(np.float32))   # (H, W, 3) map-frame directions
        rays[np.abs(rays) < 1e-9] = 1e-9
        inv = 1.0 / rays

        # Room structure: where each ray leaves the room box [0, W] x [0, D] x [0, H].
        size = self.room.size.astype(np.float32)
        t_axis = (np.where(rays > 0, size, np.float32(0)) - pos.astype(np.float32)) * inv
        exit_axis = np.argmin(t_axis, axis=-1)
        depth = np.take_along_axis(t_axis, exit_axis[..., None], -1)[..., 0]
        # Surface id: 0 wall x=0, 1 wall x=W, 2 wall y=0, 3 wall y=D, 4 floor, 5 ceiling
        positive = np.take_along_axis(rays, exit_axis[..., None], -1)[..., 0] > 0
        surface = 2 * exit_axis + positive
        prim_id = np.zeros((h, w), dtype=np.int32)          # 0 structure, i + 1 primitive i
        obj_axis = np.zeros((h, w), dtype=np.int8)          # entry axis of the winning primitive hit

        n = len(self._boxes)
        unoccluded = np.zeros(n, dtype=np.int64)
        amodal, boxes_2d, rects, inside = self._project_boxes(rot_wc, pos)
        if not self.cull:
            rects = np.where(rects[:, 2:3] > rects[:, 0:1], [[0, 0, w, h]], rects)
        # each object's parts within its amodal box's rectangle, then the clutter in its own
        clutter_rects = (self._project_boxes(rot_wc, pos, self._clutter_corners)[2]
                         if len(self._clutter_corners) else np.zeros((0, 4), np.int64))
        prim_rects = np.concatenate([rects[self._prim_owner[self._prim_owner >= 0]], clutter_rects])
        seen = None
        for i, box in enumerate(self._prims):
            u0, v0, u1, v1 = prim_rects[i]
            if u1 <= u0 or v1 <= v0:
                continue
            k = self._prim_owner[i]
            c, s = np.float32(np.cos(box[6])), np.float32(np.sin(box[6]))
            rel = pos - box[:3]
            ol = np.array([c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1], rel[2]], np.float32)
            half = (box[3:6] / 2).astype(np.float32)
            d = rays[v0:v1, u0:u1]
            dx = c * d[..., 0] + s * d[..., 1]
            dy = -s * d[..., 0] + c * d[..., 1]
            t_near = np.full(dx.shape, -np.inf, np.float32)
            t_far = np.full(dx.shape, np.inf, np.float32)
            axis = np.zeros(dx.shape, np.int8)
            for j, di in enumerate((dx, dy, d[..., 2])):     # slab test per axis
                with np.errstate(divide='ignore'):
                    inv_d = 1.0 / di
                ta, tb = (-half[j] - ol[j]) * inv_d, (half[j] - ol[j]) * inv_d
                enter, leave = np.minimum(ta, tb), np.maximum(ta, tb)
                later = enter > t_near
                t_near = np.where(later, enter, t_near)
                axis[later] = j
                np.minimum(t_far, leave, out=t_far)
            hit = (t_near <= t_far) & (t_near > _NEAR)
            if k >= 0:                   # the object's silhouette ignoring occlusion: its parts' union
                first = i == 0 or self._prim_owner[i - 1] != k
                last = i + 1 == len(self._prims) or self._prim_owner[i + 1] != k
                if first and last:
                    unoccluded[k] = np.count_nonzero(hit)
                else:
                    seen = hit.copy() if first else seen | hit
                    if last:
                        unoccluded[k] = np.count_nonzero(seen)
            closer = hit & (t_near < depth[v0:v1, u0:u1])
            if not np.any(closer):
                continue
            depth[v0:v1, u0:u1][closer] = t_near[closer]
            prim_id[v0:v1, u0:u1][closer] = i + 1
            obj_axis[v0:v1, u0:u1][closer] = axis[closer]

        instance = self._instance_of[prim_id].astype(np.int32)
        visible = np.bincount(instance.ravel(), minlength=n + 1)[1:].astype(np.int64)
        amodal = np.where(inside, unoccluded, amodal)
        rgb = self._shade(pos, rays, depth, prim_id, surface, obj_axis, prim_rects)

        rng = np.random.default_rng(0) if rng is None else rng
        nm = self.noise
        rgb *= 255.0
        if nm.color_sigma > 0:
            rgb += rng.normal(0.0, nm.color_sigma, rgb.shape).astype(np.float32)
        rgb = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
        depth_true = depth.astype(np.float32)
        noisy = self._depth_noise(depth_true, rng)
        if nm.projector_baseline_m > 0 or nm.flying_pixel_fraction > 0 or nm.dark_dropout_prob > 0:
            noisy = self._stereo_artefacts(noisy, depth_true, rgb, rng)
        return RenderOutput(rgb, noisy, depth_true, instance, visible, unoccluded, amodal, boxes_2d)

    def _albedo_at(self, tile: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        scale = self._tile_scale[tile]
        iu = np.floor(u * scale).astype(np.int64) % _TILE
        iv = np.floor(v * scale).astype(np.int64) % _TILE
        return self._tiles[tile, iv, iu]

    def _shade(self, pos, rays, depth, prim_id, surface, obj_axis, rects):
        """Lambertian shading of albedo textures fixed in object (part) coordinates."""
        h, w = prim_id.shape
        flat_inst = prim_id.ravel()
        rays_flat = rays.reshape(-1, 3)
        depth_flat = depth.ravel()
        albedo = np.zeros((h * w, 3), dtype=np.uint8)
        normal = np.zeros((h * w, 3), dtype=np.float32)
        pos32 = pos.astype(np.float32)

        # Room structure (surfaces 0-5: x=0, x=W, y=0, y=D, floor, ceiling)
        idx0 = np.flatnonzero(flat_inst == 0)
        surf = surface.ravel()[idx0]
        for sid in range(6):
            idx = idx0[surf == sid]
            if not len(idx):
                continue
            p = pos32 + rays_flat[idx] * depth_flat[idx, None]
            axis = sid // 2
            u, v = (p[:, 1], p[:, 2]) if axis == 0 else (p[:, 0], p[:, 2]) if axis == 1 else (p[:, 0], p[:, 1])
            albedo[idx] = self._albedo_at(sid, u, v)
            normal[idx, axis] = -1.0 if sid % 2 else 1.0      # pointing into the room
        # Primitives (objects' parts, clutter): each stays inside its projected rectangle
        for k in range(len(self._prims)):
            u0, v0, u1, v1 = rects[k]
            if u1 <= u0 or v1 <= v0:
                continue
            vv, uu = np.nonzero(prim_id[v0:v1, u0:u1] == k + 1)
            if not len(vv):
                continue
            idx = (vv + v0) * w + (uu + u0)
            box = self._box_table[k + 1]
            c, s = np.cos(box[6]), np.sin(box[6])
            rel = pos32 + rays_flat[idx] * depth_flat[idx, None] - box[:3]
            local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], -1)
            axis = obj_axis.ravel()[idx].astype(np.int64)
            rows = np.arange(len(idx))
            sign = np.sign(local[rows, axis])
            # surface coordinates: the two local coordinates spanning the face (m)
            other1 = np.where(axis == 0, 1, 0)
            other2 = np.where(axis == 2, 1, 2)
            u = local[rows, other1] + box[3 + other1] / 2
            v = local[rows, other2] + box[3 + other2] / 2
            albedo[idx] = self._albedo_at(self._prim_tile[k], u, v)
            n_local = np.zeros((len(idx), 3), dtype=np.float32)
            n_local[rows, axis] = sign
            normal[idx] = np.stack([c * n_local[:, 0] - s * n_local[:, 1],
                                    s * n_local[:, 0] + c * n_local[:, 1], n_local[:, 2]], -1)
        lambert = np.clip(normal @ _LIGHT.astype(np.float32), 0.0, 1.0)
        # a little bounce light, so faces turned away from the light still differ
        bounce = 0.08 * np.abs(normal @ np.array([0.8, -0.6, 0.0], dtype=np.float32))
        shade = (_AMBIENT + _DIFFUSE * lambert + bounce) * np.float32(1 / 255)
        return (albedo * shade[:, None]).reshape(h, w, 3)

    def _stereo_artefacts(self, noisy, depth, rgb, rng) -> np.ndarray:
        """An active-stereo camera's failures: the projector's shadow (an invalid band on the
        background beside each foreground edge, as wide as the projector's parallax between
        the two depths), flying pixels (a depth between the two sides of an edge) and depth
        lost on dark surfaces."""
        nm = self.noise
        out = noisy.copy()
        h, w = depth.shape
        if nm.projector_baseline_m > 0:           # projector to the camera's right: shadows left of edges
            near, far = depth[:, 1:], depth[:, :-1]     # a foreground starting at column c + 1
            with np.errstate(invalid='ignore', divide='ignore'):
                width = self.intrinsics.fx * nm.projector_baseline_m * (1.0 / near - 1.0 / far)
            width = np.where(far - near > 0.05, width, 0.0)
            for k in range(int(np.ceil(np.nanmax(width, initial=0.0)))):
                rows, cols = np.nonzero(width > k)
                cols = cols - k
                ok = cols >= 0
                out[rows[ok], cols[ok]] = np.nan
        if nm.flying_pixel_fraction > 0:
            jump = np.zeros(depth.shape, bool)
            jump[:, 1:] |= np.abs(np.diff(depth, axis=1)) > 0.1
            jump[1:, :] |= np.abs(np.diff(depth, axis=0)) > 0.1
            fly = jump & (rng.random(depth.shape) < nm.flying_pixel_fraction) & np.isfinite(out)
            left = np.concatenate([depth[:, :1], depth[:, :-1]], 1)
            right = np.concatenate([depth[:, 1:], depth[:, -1:]], 1)
            mix = rng.random(depth.shape).astype(np.float32)
            out[fly] = (mix * left + (1 - mix) * right)[fly]
        if nm.dark_dropout_prob > 0:
            luma = rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) / 255.0
            out[(luma < nm.dark_dropout_below) & (rng.random(depth.shape) < nm.dark_dropout_prob)] = np.nan
        return out

    def _depth_noise(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        nm = self.noise
        fb = nm.depth_focal_px * nm.depth_baseline_m
        disparity = fb / depth
        if nm.disparity_sigma_px > 0:
            h, w = depth.shape
            block = max(int(nm.depth_noise_block_px), 1)
            coarse = rng.normal(0.0, nm.disparity_sigma_px, (h // block + 1, w // block + 1))
            disparity = disparity + np.repeat(np.repeat(coarse, block, 0), block, 1)[:h, :w]
        if nm.disparity_subpixel > 0:
            disparity = np.round(disparity * nm.disparity_subpixel) / nm.disparity_subpixel
        with np.errstate(divide='ignore'):
            out = (fb / disparity).astype(np.float32)
        holes = ~(disparity > 0)
        if nm.depth_hole_fraction > 0:
            holes |= rng.random(depth.shape) < nm.depth_hole_fraction
        if nm.depth_edge_hole_fraction > 0:
            jump = np.zeros(depth.shape, dtype=bool)
            jump[:, 1:] |= np.abs(np.diff(depth, axis=1)) > 0.1
            jump[1:, :] |= np.abs(np.diff(depth, axis=0)) > 0.1
            holes |= jump & (rng.random(depth.shape) < nm.depth_edge_hole_fraction)
        holes |= depth > nm.max_depth_m
        out[holes] = np.nan
        return out
