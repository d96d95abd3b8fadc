"""Run by ParaView's ``pvbatch`` (tests/test_paraview.py), not by pytest: opens each file as a
double-click does, with ParaView's default reader for its suffix (``OpenDataFile``), and
prints one JSON line: per file, the reader, the point and cell counts, and each array's
component count and range (its magnitude's, for vectors). With ``--warp PNG`` it also renders
the first file warped by its ``displacement`` (*Warp By Vector*) to PNG.

    xvfb-run -a -s -noreset pvbatch tests/paraview_probe.py $PWD/out/displacement.xdmf \
        --warp warp.png
"""

import argparse
import json
import math

from paraview import simple


def _arrays(data) -> dict:
    out = {}
    for name in data.keys():
        a = data[name]
        lo, hi = a.GetRange(-1 if a.GetNumberOfComponents() > 1 else 0)
        out[name] = {"components": a.GetNumberOfComponents(),
                     "range": [None if math.isnan(v) else v for v in (lo, hi)]}
    return out


def probe(path: str) -> dict:
    reader = simple.OpenDataFile(path)
    if reader is None:
        return {"reader": None}
    reader.UpdatePipeline()
    info = reader.GetDataInformation()
    return {"reader": reader.GetXMLName(), "points": info.GetNumberOfPoints(),
            "cells": info.GetNumberOfCells(), "point_data": _arrays(reader.PointData),
            "cell_data": _arrays(reader.CellData)}


def warp(path: str, png: str) -> None:
    """*Warp By Vector* on ``displacement``, coloured by its magnitude, seen from the side."""
    warped = simple.WarpByVector(Input=simple.OpenDataFile(path), Vectors=["POINTS",
                                                                             "displacement"])
    view = simple.CreateRenderView(ViewSize=[800, 700], OrientationAxesVisibility=0)
    shown = simple.Show(warped, view)
    simple.ColorBy(shown, ("POINTS", "displacement", "Magnitude"))
    shown.SetScalarBarVisibility(view, True)
    view.CameraPosition, view.CameraViewUp = [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]
    view.ResetCamera()
    simple.SaveScreenshot(png, view)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("files", nargs="+")
    ap.add_argument("--warp", help="PNG of the first file warped by its displacement")
    args = ap.parse_args()
    print(json.dumps({f: probe(f) for f in args.files}))
    if args.warp:
        warp(args.files[0], args.warp)
