"""Built-in objects made of simple solids blended together (sdf.py), meshed by marching cubes (sdf_mesh.py).

Each maker returns a SolidScene: the signed distance function and the box and voxel to mesh it in. Its `mesh()` is a
new watertight trimesh.Trimesh in metres, standing on z = 0 and centred on the z axis. Faces point +y where an
object has a front. The voxel sizes keep the meshing error well under a millimetre (marching cubes on a smooth
surface of radius R errs by about voxel^2 / 8R: 0.04 mm on the teddy's ear (7 mm radius) at 1.5 mm voxels) and the
build at a second or two.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .sdf import (Shape, box, capsule, cylinder, ellipsoid, intersect, rotated, shell, smooth_union, sphere,
                  subtract, torus)
from .sdf_mesh import mesh_sdf

VOXEL_M = 0.0015
"""Default meshing voxel (metres)."""


@dataclass(frozen=True)
class SolidScene:
    """A shape (metres) and where to mesh it: |x|, |y| <= half_xy, 0 <= z <= height, voxels of `voxel`."""

    shape: Shape
    half_xy: float
    height: float
    voxel: float = VOXEL_M

    def mesh(self):
        return mesh_sdf(self.shape, self.half_xy, self.height, self.voxel)


def teddy():
    """A sitting teddy bear, 0.25 m: round body and head, muzzle and nose, two thin ears, arms with paws, legs
    stretched forward with big feet."""
    parts = [ellipsoid((0, 0, 0.075), (0.062, 0.054, 0.085)),        # body, its bottom cut flat to sit on
             sphere((0, 0.004, 0.183), 0.054),                          # head
             ellipsoid((0, 0.048, 0.170), (0.026, 0.022, 0.019)),       # muzzle
             sphere((0, 0.068, 0.178), 0.009)]                          # nose
    for side in (-1, 1):
        ear = ellipsoid((0, 0, 0), (0.019, 0.007, 0.019))
        ear = rotated(ear, (0, 1, 0), side * 0.45)
        parts.append(lambda x, y, z, ear=ear, s=side: ear(x - s * 0.040, y + 0.004, z - 0.228))
        parts.append(capsule((side * 0.050, 0.006, 0.125), (side * 0.074, 0.044, 0.070), 0.017))   # arm
        parts.append(sphere((side * 0.076, 0.050, 0.064), 0.021))                                # paw
        parts.append(capsule((side * 0.034, 0.020, 0.030), (side * 0.046, 0.086, 0.026), 0.025))  # leg
        parts.append(ellipsoid((side * 0.048, 0.102, 0.032), (0.023, 0.014, 0.032)))            # foot
    return SolidScene(smooth_union(0.010, *parts), 0.13, 0.26)


def _head(base_z: float):
    """A sculpted head whose neck starts at base_z: neck, skull, jaw, nose, brow, ears, eye sockets; 0.29 m from the
    neck's foot to the top."""
    z = base_z
    parts = [capsule((0, 0, z), (0, 0.004, z + 0.115), 0.040),            # neck
             ellipsoid((0, -0.006, z + 0.190), (0.074, 0.088, 0.098)),    # skull
             ellipsoid((0, 0.030, z + 0.132), (0.052, 0.058, 0.048)),     # jaw and chin
             capsule((0, 0.084, z + 0.192), (0, 0.094, z + 0.160), 0.011),  # nose
             ellipsoid((0, 0.060, z + 0.202), (0.060, 0.030, 0.014))]     # brow
    for side in (-1, 1):
        parts.append(ellipsoid((side * 0.073, -0.008, z + 0.180), (0.011, 0.022, 0.030)))   # ear
    head = smooth_union(0.016, *parts)
    sockets = [sphere((side * 0.030, 0.088, z + 0.182), 0.015) for side in (-1, 1)]
    return subtract(head, *sockets)


def head():
    """A sculpted head on a square plinth, 0.35 m: a 14 cm square block 6 cm tall, neck, skull, nose, ears."""
    plinth = box((0, 0, 0.030), (0.070, 0.070, 0.030), rounding=0.002)
    return SolidScene(smooth_union(0.006, plinth, _head(0.058)), 0.12, 0.36)


def duck():
    """A small bath duck, 0.15 m: an egg-shaped body with a raised tail, a round head on a short neck, a flat beak."""
    tail = rotated(ellipsoid((0, 0, 0), (0.022, 0.030, 0.014)), (1, 0, 0), -0.5)
    parts = [ellipsoid((0, 0, 0.040), (0.046, 0.070, 0.046)),
             lambda x, y, z: tail(x, y + 0.060, z - 0.068),
             sphere((0, 0.040, 0.117), 0.032),
             ellipsoid((0, 0.078, 0.110), (0.015, 0.024, 0.007))]
    return SolidScene(smooth_union(0.018, *parts), 0.11, 0.16)


def _rungs(tops, feet, t: float, radius: float) -> list:
    """Capsules of `radius` (metres) joining each leg to the next, all round, at the fraction t of the way from the
    legs' feet to their tops (points (3,) in metres)."""
    out = []
    for k in range(len(tops)):
        j = (k + 1) % len(tops)
        out.append(capsule(feet[k] + t * (tops[k] - feet[k]), feet[j] + t * (tops[j] - feet[j]), radius))
    return out


def stool():
    """A three-legged stool, 0.20 m: a round seat, dished 4 mm, on three splayed 12 mm legs joined by 8 mm rungs
    (thin parts)."""
    dish = sphere((0, 0, 0.196 + 0.705), 0.705)  # a cap 4 mm deep and 15 cm across
    parts = [subtract(cylinder((0, 0), 0.090, 0.180, 0.200, rounding=0.003), dish)]
    feet, tops = [], []
    for k in range(3):
        a = 2 * math.pi * k / 3 + math.pi / 2
        c, s = math.cos(a), math.sin(a)
        tops.append(np.array([0.060 * c, 0.060 * s, 0.182]))
        feet.append(np.array([0.085 * c, 0.085 * s, -0.010]))
        parts.append(capsule(tops[-1], feet[-1], 0.006))
    parts += _rungs(tops, feet, (0.070 + 0.010) / 0.192, 0.004)  # rungs at 7 cm between neighbouring legs
    return SolidScene(smooth_union(0.003, *parts), 0.10, 0.21, 0.0012)


def mug():
    """A tall mug, 0.15 m: a 5 mm wall round a 9 cm bore, an 8 mm floor, a ring handle on one side (concave, a
    hole through the handle)."""
    outer = cylinder((0, 0), 0.050, -0.01, 0.150, rounding=0.003)
    bore = cylinder((0, 0), 0.045, 0.008, 0.2, rounding=0.004)
    body = subtract(outer, bore)
    ring = rotated(torus((0, 0, 0), 0.036, 0.007), (1, 0, 0), math.pi / 2)
    handle = subtract(lambda x, y, z: ring(x - 0.056, y, z - 0.078), cylinder((0, 0), 0.046, -0.01, 0.2))
    return SolidScene(smooth_union(0.004, body, handle), 0.12, 0.16)


def bowl():
    """A wide salad bowl, 0.30 m across and 0.11 m tall: a 6 mm wall on a foot ring (large, shallow concavity)."""
    outer = ellipsoid((0, 0, 0.118), (0.150, 0.150, 0.110))
    wall = intersect(shell(outer, 0.006), lambda x, y, z: z - 0.110)
    foot = subtract(cylinder((0, 0), 0.060, -0.01, 0.016), cylinder((0, 0), 0.052, -0.02, 0.012))
    return SolidScene(smooth_union(0.004, wall, foot), 0.16, 0.12)


def head_on_can():
    """A mannequin head on a can, 0.50 m: a 12 cm wide, 22 cm tall cylinder with rounded rims, the head above."""
    can = cylinder((0, 0), 0.060, -0.01, 0.220, rounding=0.004)
    return SolidScene(smooth_union(0.006, can, _head(0.218)), 0.12, 0.52)


def chair():
    """A small chair, 0.26 m: a 12 cm square seat 12 mm thick on four 10 mm legs, a back of two posts, a top rail and
    a slat (thin parts, a gap between seat and rail)."""
    seat = box((0, 0, 0.125), (0.060, 0.060, 0.006), rounding=0.002)
    parts = [seat]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(capsule((sx * 0.052, sy * 0.052, -0.004), (sx * 0.052, sy * 0.052, 0.120), 0.005))
        parts.append(capsule((sx * 0.052, -0.054, 0.130), (sx * 0.054, -0.064, 0.255), 0.005))   # back posts
    parts.append(box((0, -0.064, 0.245), (0.056, 0.005, 0.012), rounding=0.002))                  # top rail
    parts.append(box((0, -0.060, 0.190), (0.054, 0.004, 0.008), rounding=0.002))                  # slat
    return SolidScene(smooth_union(0.003, *parts), 0.08, 0.27, 0.0012)


def snowman():
    """A snowman of three stacked balls, 0.28 m, with a carrot nose and two stubby arms (smooth, round)."""
    parts = [sphere((0, 0, 0.068), 0.070), sphere((0, 0, 0.172), 0.050), sphere((0, 0, 0.245), 0.036),
             capsule((0, 0.030, 0.248), (0, 0.062, 0.244), 0.006),                                   # nose
             capsule((0.045, 0, 0.180), (0.090, 0.010, 0.205), 0.007),                              # arms
             capsule((-0.045, 0, 0.180), (-0.090, 0.010, 0.205), 0.007)]
    return SolidScene(smooth_union(0.012, *parts), 0.11, 0.29)


def vase():
    """A vase, 0.25 m: a round belly 15 cm across, a narrow neck open at the top (a 4 cm mouth), a 5 mm wall (a deep
    concavity seen only through its mouth)."""
    outer = smooth_union(0.025, ellipsoid((0, 0, 0.085), (0.075, 0.075, 0.090)),  # sunk 5 mm: a flat foot
                         cylinder((0, 0), 0.025, 0.150, 0.250, rounding=0.003))
    # The shell's wall at the bottom lies below z = 0 (the foot is sunk 5 mm), where the ground cuts it away: the
    # floor is the outer solid's slice from the ground up to 5 mm, as thick as the wall.
    floor = intersect(outer, lambda x, y, z: z - 0.005)
    wall = smooth_union(0.002, shell(outer, 0.005), floor)
    open_top = subtract(wall, cylinder((0, 0), 0.020, 0.150, 0.30))
    return SolidScene(intersect(open_top, lambda x, y, z: -z), 0.09, 0.26)


def ring_stand():
    """A ring on a stand, 0.24 m: a 16 cm upright ring of 24 mm thick section on a post and a round foot (a hole
    through, a thin round section)."""
    ring = rotated(torus((0, 0, 0), 0.070, 0.012), (1, 0, 0), math.pi / 2)
    parts = [lambda x, y, z: ring(x, y, z - 0.155),
             capsule((0, 0, 0.010), (0, 0, 0.080), 0.010),
             cylinder((0, 0), 0.055, 0.0, 0.014, rounding=0.003)]
    return SolidScene(smooth_union(0.008, *parts), 0.10, 0.25)


def cat():
    """A sitting cat, 0.23 m: a pear-shaped body, a round head with two pointed ears and a muzzle, a tail curled
    along the ground round its front paws."""
    parts = [ellipsoid((0, -0.005, 0.065), (0.055, 0.060, 0.068)),
             ellipsoid((0, 0.012, 0.112), (0.040, 0.040, 0.050)),       # chest
             sphere((0, 0.020, 0.170), 0.040),                           # head
             ellipsoid((0, 0.055, 0.160), (0.020, 0.014, 0.013))]        # muzzle
    for side in (-1, 1):
        ear = rotated(ellipsoid((0, 0, 0), (0.014, 0.005, 0.022)), (0, 1, 0), side * 0.35)
        parts.append(lambda x, y, z, ear=ear, s=side: ear(x - s * 0.024, y - 0.018, z - 0.208))
        parts.append(capsule((side * 0.022, 0.040, 0.060), (side * 0.022, 0.058, 0.012), 0.012))   # front legs
    tail = [(0.055, -0.030, 0.010), (0.070, 0.020, 0.010), (0.050, 0.070, 0.010), (0.000, 0.085, 0.010)]
    parts += [capsule(a, b, 0.009) for a, b in zip(tail, tail[1:])]
    return SolidScene(smooth_union(0.010, *parts), 0.11, 0.23)


def lighthouse():
    """A lighthouse, 0.34 m: a tower tapering from 13 to 8 cm across, a gallery ring near its top, a lantern and a
    dome (tall: its top is far above the point the views aim at)."""
    def tower(x, y, z):
        r = 0.065 - 0.025 * np.clip(z / 0.26, 0.0, 1.0)
        side = np.sqrt(x * x + y * y) - r
        return np.maximum(side, np.maximum(-z, z - 0.26))
    parts = [tower, cylinder((0, 0), 0.058, 0.255, 0.265, rounding=0.002),   # gallery
             cylinder((0, 0), 0.030, 0.262, 0.305, rounding=0.002),           # lantern
             sphere((0, 0, 0.305), 0.033)]                                     # dome
    return SolidScene(smooth_union(0.004, *parts), 0.08, 0.345)


def candlestick():
    """A candlestick, 0.27 m: a round foot 11 cm across, a 12 mm column 18 cm tall, a drip pan 7 cm across and a
    candle on top (a thin column between two masses)."""
    parts = [cylinder((0, 0), 0.055, 0.0, 0.012, rounding=0.003),
             capsule((0, 0, 0.010), (0, 0, 0.196), 0.006),
             subtract(cylinder((0, 0), 0.035, 0.192, 0.208, rounding=0.002), cylinder((0, 0), 0.030, 0.198, 0.3)),
             cylinder((0, 0), 0.011, 0.196, 0.270, rounding=0.002)]
    return SolidScene(smooth_union(0.004, *parts), 0.06, 0.28, 0.0012)


def kettle():
    """A kettle, 0.18 m: a round body 17 cm across with a flat foot, a lid knob, a spout rising at the front and a
    14 mm handle arching over the back (smooth, a loop)."""
    body = intersect(ellipsoid((0, 0, 0.075), (0.085, 0.085, 0.085)), lambda x, y, z: -z)
    ring = rotated(torus((0, 0, 0), 0.050, 0.007), (0, 1, 0), math.pi / 2)
    parts = [body, sphere((0, 0, 0.162), 0.014),                               # lid knob
             capsule((0, 0.055, 0.060), (0, 0.125, 0.135), 0.011),             # spout
             lambda x, y, z: ring(x, y + 0.070, z - 0.115)]                     # handle
    return SolidScene(smooth_union(0.008, *parts), 0.14, 0.19)


def pear():
    """A pear, 0.20 m: a round bottom 11 cm across and a narrower top blended into it, a stalk (smooth, organic)."""
    fruit = smooth_union(0.040, ellipsoid((0, 0, 0.052), (0.055, 0.055, 0.060)), sphere((0, 0, 0.130), 0.034))
    parts = [intersect(fruit, lambda x, y, z: -z), capsule((0, 0, 0.160), (0.008, 0, 0.195), 0.0035)]
    return SolidScene(smooth_union(0.004, *parts), 0.07, 0.20, 0.0012)


def plant_stand():
    """A plant stand, 0.18 m: a 13 cm square top 15 mm thick on four splayed 10 mm legs, joined near the floor by
    6 mm braces (thin parts: for tuning what thin legs and rungs need)."""
    parts = [box((0, 0, 0.1725), (0.065, 0.065, 0.0075), rounding=0.002)]
    tops, feet = [], []
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        tops.append(np.array([0.048 * sx, 0.048 * sy, 0.168]))
        feet.append(np.array([0.068 * sx, 0.068 * sy, -0.008]))
        parts.append(capsule(tops[-1], feet[-1], 0.005))
    parts += _rungs(tops, feet, (0.055 + 0.008) / 0.176, 0.003)  # braces 5.5 cm above the floor
    return SolidScene(smooth_union(0.003, *parts), 0.08, 0.185, 0.0010)


def side_table():
    """A side table, 0.205 m: a round top 20 cm across and 15 mm thick, overhanging four splayed 12 mm legs by 4 cm
    (a wide overhang on thin parts: the space under it is seen only between the legs, from low views)."""
    parts = [cylinder((0, 0), 0.100, 0.190, 0.205, rounding=0.003)]
    for k in range(4):
        a = 2 * math.pi * k / 4 + math.pi / 4
        c, s = math.cos(a), math.sin(a)
        parts.append(capsule((0.060 * c, 0.060 * s, 0.192), (0.085 * c, 0.085 * s, -0.010), 0.006))
    return SolidScene(smooth_union(0.003, *parts), 0.11, 0.21, 0.0012)


def easel():
    """A table easel, 0.30 m: two 10 mm front legs and a 10 mm back leg meeting at the top, a 6 mm crossbar and a
    ledge 12 cm wide holding a board 18 x 13 cm, 6 mm thick, on a head that joins the legs (thin legs, a flat plate
    leaning back)."""
    top = np.array([0.0, 0.0, 0.288])
    parts = [box(top, (0.020, 0.010, 0.010), rounding=0.003)]                              # the head joining the legs
    for sx in (-1, 1):
        parts.append(capsule(top + (sx * 0.012, 0.004, 0), (sx * 0.070, 0.045, 0.0), 0.005))   # front legs
    parts.append(capsule(top + (0, -0.006, 0), (0.0, -0.080, 0.0), 0.005))                         # back leg
    parts.append(capsule((-0.058, 0.037, 0.050), (0.058, 0.037, 0.050), 0.003))                    # crossbar
    tilt = math.atan2(0.045, 0.295)
    board = rotated(box((0, 0, 0), (0.090, 0.003, 0.065), rounding=0.0015), (1, 0, 0), tilt)
    parts.append(lambda x, y, z: board(x, y - 0.027, z - 0.180))                                  # board on the legs
    parts.append(box((0, 0.046, 0.110), (0.060, 0.012, 0.004), rounding=0.0015))                 # ledge
    return SolidScene(smooth_union(0.003, *parts), 0.10, 0.30, 0.0010)


def coat_rack():
    """A coat rack, 0.32 m: a 12 mm pole on four 10 mm feet splayed 12 cm, four 8 mm hooks near its top, a ball
    finial (a thin pole, thin parts sticking out)."""
    parts = [capsule((0, 0, 0.010), (0, 0, 0.300), 0.006), sphere((0, 0, 0.302), 0.014)]
    for k in range(4):
        a = math.pi / 4 + k * math.pi / 2
        c, s = math.cos(a), math.sin(a)
        parts.append(capsule((0.008 * c, 0.008 * s, 0.040), (0.060 * c, 0.060 * s, 0.004), 0.005))  # feet
        b = a + math.pi / 4
        cb, sb = math.cos(b), math.sin(b)
        parts.append(capsule((0, 0, 0.255), (0.045 * cb, 0.045 * sb, 0.275), 0.004))               # hooks
    return SolidScene(smooth_union(0.003, *parts), 0.08, 0.32, 0.0010)


SOLID_SCENES = {"teddy": teddy, "head": head, "duck": duck, "stool": stool, "mug": mug, "bowl": bowl,
                "head-on-can": head_on_can, "chair": chair, "snowman": snowman, "vase": vase, "ring-stand": ring_stand,
                "cat": cat, "lighthouse": lighthouse, "candlestick": candlestick, "kettle": kettle, "pear": pear,
                "plant-stand": plant_stand, "easel": easel, "coat-rack": coat_rack,
                "side-table": side_table}
"""Built-in scene name -> maker of its SolidScene."""


__all__ = ["SolidScene", "SOLID_SCENES", "VOXEL_M", "teddy", "head", "duck", "stool", "mug", "bowl", "head_on_can"]
