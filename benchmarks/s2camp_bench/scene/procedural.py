"""A small procedural world rendered by analytic ray casting (numpy, vectorized over rays).

z up, ground plane z = 0, textured primitives near the origin and a far textured background sphere (unbounded, as
mip-NeRF 360). View-independent shading (Lambert + ambient + hard shadows, emissive background): each surface point
has one colour in all images. Solid textures with centimetre detail, so small camera errors change the images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BACKGROUND_RADIUS = 40.0
"""Radius of the background sphere (the cameras sit a few units from the origin)."""

LOOK_AT = np.array([0.0, 0.0, 0.45])
"""Point the camera ring looks at."""

SCENE_RADIUS = 1.8
"""Radius (about the z axis) that holds every foreground primitive; cameras must stay outside it."""

_SUN = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])
_AMBIENT, _DIFFUSE = 0.38, 0.62
_EPS = 1e-9

# Material ids (index into the hit record).
NONE, GROUND, SPHERE0, SPHERE1, SPHERE2, BOX, BACKGROUND = range(7)

# (centre, radius, material) of the foreground spheres.
_SPHERES = (
    (np.array([0.0, 0.0, 0.7]), 0.7, SPHERE0),
    (np.array([1.15, -0.75, 0.35]), 0.35, SPHERE1),
    (np.array([-0.55, 1.15, 0.45]), 0.45, SPHERE2),
)
_BOX_MIN = np.array([-1.55, -1.25, 0.0])
_BOX_MAX = np.array([-0.75, -0.45, 0.9])


@dataclass
class Hits:
    """First intersections of a batch of rays."""

    t: np.ndarray  # [N] ray parameter of the hit (inf where nothing was hit)
    material: np.ndarray  # [N] material id
    normal: np.ndarray  # [N, 3] unit outward normal (inward for the background sphere)

    def points(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        return origins + self.t[:, None] * directions


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice point (uint32 avalanche hash)."""
    with np.errstate(over="ignore"):
        h = (ix.astype(np.int64).astype(np.uint32) * np.uint32(0x8DA6B343)) ^ (
            iy.astype(np.int64).astype(np.uint32) * np.uint32(0xD8163841)
        )
        h ^= iz.astype(np.int64).astype(np.uint32) * np.uint32(0xCB1AB31F)
        h ^= np.uint32((seed * 0x9E3779B1) & 0xFFFFFFFF)
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x7FEB352D)
        h ^= h >> np.uint32(15)
        h *= np.uint32(0x846CA68B)
        h ^= h >> np.uint32(16)
    return h.astype(np.float64) / 4294967296.0


def value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Trilinear value noise with smoothstep fade, values in [0, 1). ``p``: [N, 3]."""
    cell = np.floor(p)
    f = p - cell
    w = f * f * (3.0 - 2.0 * f)
    i = cell.astype(np.int64)
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


def fbm(p: np.ndarray, seed: int, octaves: int = 4) -> np.ndarray:
    """Fractal sum of value noise, normalized to [0, 1)."""
    total, amplitude, norm = np.zeros(p.shape[0]), 1.0, 0.0
    for k in range(octaves):
        total += amplitude * value_noise(p * (2.0**k), seed + 101 * k)
        norm += amplitude
        amplitude *= 0.5
    return total / norm


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + (np.asarray(b) - a) * np.clip(t, 0.0, 1.0)[:, None]


def _rgb(*values: float) -> np.ndarray:
    return np.array(values, dtype=np.float64)


def intersect(origins: np.ndarray, directions: np.ndarray, foreground_only: bool = False) -> Hits:
    """First hit of each ray (unit ``directions`` [N, 3]) with the world; ``foreground_only`` skips the
    ground and the background (used for shadow rays)."""
    n = origins.shape[0]
    best_t = np.full(n, np.inf)
    material = np.full(n, NONE, dtype=np.int64)
    normal = np.zeros((n, 3))

    def take(t: np.ndarray, mat: int, nrm: np.ndarray) -> None:
        closer = (t > 1e-7) & (t < best_t)
        best_t[closer] = t[closer]
        material[closer] = mat
        normal[closer] = nrm[closer]

    for centre, radius, mat in _SPHERES:
        oc = origins - centre
        b = np.einsum("ij,ij->i", oc, directions)
        c = np.einsum("ij,ij->i", oc, oc) - radius * radius
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            t = np.where(disc > 0.0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        t = np.where(t > 1e-7, t, np.inf)  # cameras are outside; a shadow ray leaving the surface misses
        take(t, mat, (origins + t[:, None] * directions - centre) / radius)
    # Axis-aligned box (slab method); the normal is the axis of the slab entered last.
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(directions) < _EPS, _EPS, directions)
        t0 = (_BOX_MIN - origins) * inv
        t1 = (_BOX_MAX - origins) * inv
    t_enter_axes = np.minimum(t0, t1)
    t_enter = t_enter_axes.max(axis=1)
    t_exit = np.maximum(t0, t1).min(axis=1)
    t_box = np.where((t_exit >= t_enter) & (t_enter > 1e-7), t_enter, np.inf)
    axis = t_enter_axes.argmax(axis=1)
    box_normal = np.zeros((n, 3))
    box_normal[np.arange(n), axis] = -np.sign(directions[np.arange(n), axis])
    take(t_box, BOX, box_normal)
    if not foreground_only:
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ground = np.where(directions[:, 2] < -_EPS, -origins[:, 2] / directions[:, 2], np.inf)
        ground_xy = origins[:, :2] + t_ground[:, None] * directions[:, :2]
        t_ground = np.where(
            np.einsum("ij,ij->i", ground_xy, ground_xy) < (0.999 * BACKGROUND_RADIUS) ** 2, t_ground, np.inf
        )
        take(t_ground, GROUND, np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, 3)))
        b = np.einsum("ij,ij->i", origins, directions)
        c = np.einsum("ij,ij->i", origins, origins) - BACKGROUND_RADIUS**2
        t_bg = -b + np.sqrt(np.maximum(b * b - c, 0.0))  # origins are inside: the far root
        take(t_bg, BACKGROUND, -(origins + t_bg[:, None] * directions) / BACKGROUND_RADIUS)
    return Hits(best_t, material, normal)


def _albedo(points: np.ndarray, material: np.ndarray, seed: int) -> np.ndarray:
    """Solid-texture colour of surface points [N, 3] in [0, 1]."""
    out = np.zeros((points.shape[0], 3))
    m = material == GROUND
    if m.any():
        p = points[m]
        tile = (np.floor(p[:, 0] / 0.5) + np.floor(p[:, 1] / 0.5)) % 2
        coarse = fbm(p * np.array([1.2, 1.2, 0.0]), seed + 1)
        fine = fbm(p * np.array([14.0, 14.0, 0.0]), seed + 2, octaves=3)
        base = _mix(_rgb(0.55, 0.47, 0.36), _rgb(0.33, 0.42, 0.30), tile)
        colour = base * (0.55 + 0.7 * coarse)[:, None] * (0.75 + 0.5 * fine)[:, None]
        frac = np.abs(((p[:, :2] + 0.25) % 0.5) - 0.25)  # distance to the nearest tile edge (grout)
        grout = np.minimum(frac[:, 0], frac[:, 1]) < 0.012
        colour[grout] *= 0.35
        out[m] = colour
    m = material == SPHERE0  # marble
    if m.any():
        p = points[m]
        vein = 0.5 + 0.5 * np.sin(9.0 * p[:, 0] + 4.0 * p[:, 2] + 7.0 * fbm(p * 3.0, seed + 3))
        grain = fbm(p * 24.0, seed + 4, octaves=2)
        out[m] = _mix(_rgb(0.85, 0.82, 0.75), _rgb(0.45, 0.18, 0.15), vein**3) * (0.8 + 0.4 * grain)[:, None]
    m = material == SPHERE1  # solid checker
    if m.any():
        p = points[m]
        cells = np.floor(p / 0.09).astype(np.int64).sum(axis=1) % 2
        out[m] = _mix(_rgb(0.95, 0.75, 0.15), _rgb(0.10, 0.25, 0.65), cells.astype(np.float64))
    m = material == SPHERE2  # noisy stripes
    if m.any():
        p = points[m]
        stripes = 0.5 + 0.5 * np.sign(np.sin(40.0 * p[:, 2] + 3.0 * fbm(p * 4.0, seed + 5)))
        out[m] = (
            _mix(_rgb(0.15, 0.55, 0.35), _rgb(0.92, 0.92, 0.88), stripes)
            * (0.8 + 0.4 * fbm(p * 20.0, seed + 6, octaves=2))[:, None]
        )
    m = material == BOX  # tiles with a random colour each
    if m.any():
        p = points[m]
        cell = np.floor(p / 0.15).astype(np.int64)
        r = _hash01(cell[:, 0], cell[:, 1], cell[:, 2], seed + 7)
        g = _hash01(cell[:, 0], cell[:, 1], cell[:, 2], seed + 8)
        b = _hash01(cell[:, 0], cell[:, 1], cell[:, 2], seed + 9)
        out[m] = (0.25 + 0.7 * np.stack([r, g, b], axis=1)) * (0.85 + 0.3 * fbm(p * 30.0, seed + 10, octaves=2))[
            :, None
        ]
    m = material == BACKGROUND  # sky, clouds and a mountain ridge, all from the direction
    if m.any():
        d = points[m] / BACKGROUND_RADIUS
        elevation = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        azimuth = np.arctan2(d[:, 1], d[:, 0])
        ring = np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros_like(azimuth)], axis=1)
        sky = _mix(_rgb(0.80, 0.86, 0.95), _rgb(0.25, 0.45, 0.85), np.sqrt(np.clip(elevation / 1.2, 0, 1)))
        clouds = np.clip((fbm(d * 5.0, seed + 11, octaves=5) - 0.45) * 3.0, 0.0, 1.0)
        colour = _mix(sky, _rgb(0.97, 0.97, 0.97), clouds)
        ridge = 0.04 + 0.14 * fbm(ring * 3.0, seed + 12, octaves=5)
        mountain = elevation < ridge
        rock = fbm(d[mountain] * 60.0, seed + 13, octaves=3)
        colour[mountain] = _mix(_rgb(0.30, 0.33, 0.30), _rgb(0.55, 0.50, 0.45), rock)
        out[m] = colour
    return out


def shade(points: np.ndarray, hits: Hits, seed: int) -> np.ndarray:
    """Radiance [N, 3] in [0, 1] of hit points: lit albedo, hard shadows, emissive background."""
    albedo = _albedo(points, hits.material, seed)
    lit = (hits.material != BACKGROUND) & (hits.material != NONE)
    light = np.ones(points.shape[0])
    if lit.any():
        nrm = hits.normal[lit]
        cos = np.clip(nrm @ _SUN, 0.0, None)
        origins = points[lit] + 1e-5 * nrm
        blocked = np.isfinite(intersect(origins, np.broadcast_to(_SUN, origins.shape), foreground_only=True).t)
        light[lit] = _AMBIENT + _DIFFUSE * cos * ~blocked
    return np.clip(albedo * light[:, None], 0.0, 1.0)


def trace(origins: np.ndarray, directions: np.ndarray, seed: int) -> tuple[np.ndarray, Hits]:
    """Colour [N, 3] and hits of rays (``directions`` must be unit length)."""
    hits = intersect(origins, directions)
    return shade(hits.points(origins, directions), hits, seed), hits
