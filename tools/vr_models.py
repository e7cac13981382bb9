"""Writes config/models/oru.json and receptacle.json: the seed-000 cell's ORU-like box and its receptacle frame
(+/-1/4 in clearance) on a mounting plate, in the edge-model format of calibration/models/edge_model.py.

Run from the repository root: .venv/bin/python tools/vr_models.py
"""
import json
from pathlib import Path


def box(x0, x1, y0, y1, z0, z1):
    v = [[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)]
    # index = x + 2*y + 4*z
    faces = [[0, 2, 6, 4], [1, 5, 7, 3],   # -x, +x
             [0, 4, 5, 1], [2, 3, 7, 6],   # -y, +y
             [0, 1, 3, 2], [4, 6, 7, 5]]   # -z, +z
    return v, [f[::-1] for f in faces]

def frame(ow, oh, iw, ih, depth):
    # front plane y=0 (entrance, faces +y), back plane y=-depth; ring between outer and inner rectangles
    ox, oz, ix, iz = ow / 2, oh / 2, iw / 2, ih / 2
    outer = [[-ox, -oz], [ox, -oz], [ox, oz], [-ox, oz]]
    inner = [[-ix, -iz], [ix, -iz], [ix, iz], [-ix, iz]]
    v = []
    for y in (0.0, -depth):
        v += [[x, y, z] for x, z in outer] + [[x, y, z] for x, z in inner]

    def outer_at(k, b):  # outer corner k, plane b (0 front, 1 back)
        return b * 8 + k

    def inner_at(k, b):
        return b * 8 + 4 + k

    faces = []
    for k in range(4):
        n = (k + 1) % 4
        faces.append([outer_at(k, 0), inner_at(k, 0), inner_at(n, 0), outer_at(n, 0)])      # front ring (+y)
        faces.append([outer_at(k, 1), outer_at(n, 1), inner_at(n, 1), inner_at(k, 1)])      # back ring (-y)
        faces.append([outer_at(k, 0), outer_at(n, 0), outer_at(n, 1), outer_at(k, 1)])      # outer side
        faces.append([inner_at(k, 0), inner_at(k, 1), inner_at(n, 1), inner_at(n, 0)])      # inner side (faces the opening)
    return v, faces

doc = ("Edge model: vertices in `units`, faces as vertex-index loops counter-clockwise seen from outside "
       "(convex polygons). Edges are derived: face sides where the adjacent faces' normals differ, or with one face. Optional face_albedo: "
       "relative reflectance per face, used by the simulator's renderer only.")
v, f = box(-2.5, 2.5, 0.0, 4.0, -1.75, 1.75)
Path("config/models/oru.json").write_text(json.dumps({"name": "oru", "units": "in", "format": doc,
           "note": "ORU-like box, 5 x 4 x 3.5 in (x width, y depth, z height); its front face is y=0, inserted along -y",
           "vertices": v, "faces": f}))
v, f = frame(9.0, 7.5, 5.5, 4.0, 2.5)
albedo = [1.0] * len(f) + [0.5] * 6   # the plate is a darker material than the frame
pv, pf = box(-6.5, 6.5, -3.5, -2.5, -5.5, 5.5)   # the mounting plate behind the frame
f = f + [[i + len(v) for i in face] for face in pf]
v = v + pv
Path("config/models/receptacle.json").write_text(json.dumps({"name": "receptacle", "units": "in", "format": doc,
           "note": "receptacle entrance frame: outer 9 x 7.5 in, opening 5.5 x 4 in (ORU + 1/2 in: +/-1/4 in clearance), "
                   "2.5 in deep; entrance plane y=0, facing +y; mounted on a 13 x 11 x 1 in plate",
           "vertices": v, "faces": f, "face_albedo": albedo}))
