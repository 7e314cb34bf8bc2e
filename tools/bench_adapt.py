"""Benchmark of fae's fitting methods against trimesh's non-rigid ICP (nricp_amberg).

Template: the synthetic head (icosphere level 5, 10,242 vertices). Scan: a different
synthetic person, warped by a smooth random field plus fine detail, resampled (level 7
cropped to the face: about 90k vertices), with noise and holes, in millimetres and turned.
All methods get the same landmarks; nricp gets the calibrated scan and landmark pairs.
Prints time, RMS distance to the true surface, marker error and ratios against nricp.

    .venv/bin/python tools/bench_adapt.py [--nricp] [--subdivisions 7]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from fae.adapt.calibration import apply_transform
from fae.adapt.errors import compatible_closest_points, surface
from fae.adapt.geometry import per_vertex_normals
from fae.adapt.multilevel import METHODS, fit_template
from fae.adapt.synthetic import synthetic_head, synthetic_scan
from fae.adapt.transfer import scan_landmarks_in_face_frame


def truth_rms(X, F, scan, T):
    Y = apply_transform(np.linalg.inv(scan.to_scan) @ np.linalg.inv(T), X)
    _, _, d, ok = compatible_closest_points(Y, per_vertex_normals(Y, F), surface(scan.truth_vertices, scan.truth_faces), 0.02)
    return float(np.sqrt(np.mean(d[ok] ** 2)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--subdivisions", type=int, default=7)
    ap.add_argument("--template-subdivisions", type=int, default=5)
    ap.add_argument("--nricp", action="store_true", help="also run trimesh nricp_amberg (slow)")
    args = ap.parse_args()
    V, F, lm = synthetic_head(args.template_subdivisions)
    scan = synthetic_scan(11, subdivisions=args.subdivisions, face_only=True, noise=0.0002, holes=3)
    print(f"template {len(V)} vertices, scan {len(scan.vertices)} vertices")
    T, unit, names, ignored = scan_landmarks_in_face_frame(lm, scan.landmarks, scan.vertices, scan.faces)
    SV = apply_transform(T, scan.vertices)
    PL = np.array([lm[n] for n in names])
    QL = apply_transform(T, np.array([scan.landmarks[n] for n in names]))
    fit_template(V, F, PL, SV, scan.faces, QL, method="rbf")  # warm-up (Warp kernels)
    rows = []
    for method in METHODS:
        t = time.perf_counter()
        fit = fit_template(V, F, PL, SV, scan.faces, QL, method=method)
        dt = time.perf_counter() - t
        rows.append((method, dt, truth_rms(fit.vertices, F, scan, T), fit.final["marker_error"]))
    if args.nricp:
        import trimesh
        from scipy.spatial import cKDTree

        src = trimesh.Trimesh(V, F, process=False)
        tgt = trimesh.Trimesh(SV, scan.faces, process=False)
        idx = cKDTree(V).query(PL)[1]
        t = time.perf_counter()
        X = trimesh.registration.nricp_amberg(src, tgt, source_landmarks=idx, target_positions=QL)
        dt = time.perf_counter() - t
        me = float(np.sqrt(np.mean(np.sum((X[idx] - QL) ** 2, 1))))
        rows.append(("nricp_amberg", dt, truth_rms(X, F, scan, T), me))
    base = rows[-1] if args.nricp else None
    print(f"{'method':14s} {'seconds':>8s} {'truth RMS mm':>13s} {'marker mm':>10s}" + ("  speed-up  error ratio" if base else ""))
    for name, dt, err, me in rows:
        extra = f"  {base[1] / dt:8.1f}x {err / base[2]:10.2f}" if base else ""
        print(f"{name:14s} {dt:8.2f} {err * 1000:13.4f} {me * 1000:10.4f}{extra}")


if __name__ == "__main__":
    main()
