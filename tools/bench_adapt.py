"""Benchmark of fae's fitting methods against trimesh's non-rigid ICP (nricp_amberg).

Template: the shipped generic head's skin (about 9,000 vertices). Scan: another person made
from it (fae.adapt.synthetic.template_scan): warped by a smooth random field plus fine
detail, remeshed by two Loop steps (about 72k vertices on the face), without the parts no
scanner sees (inside of the mouth, lip slit, eye sockets), with noise and holes, in
millimetres and turned. All methods get the same feature points; nricp gets the
calibrated scan and the landmark pairs. Rows: "fae adapt" is everything `fae adapt` does
before writing the head (calibration of pose and unit, the default multilevel fit,
transfer of skull, jaw, muscles, eyes, teeth and tongue; not the FAP mapping), the method
rows are the skin fit alone on the calibrated scan. Prints the median seconds of
--repeat runs, RMS distance of the visible template vertices to the true surface, marker
error, and ratios against nricp measured in the same run. Single-threaded BLAS is
advised for comparable numbers:

    OMP_NUM_THREADS=1 .venv/bin/python tools/bench_adapt.py [--nricp] [--subdivisions 2] [--repeat 3]
    OMP_NUM_THREADS=1 .venv/bin/python tools/bench_adapt.py --auto    (feature point searches)
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from fae.adapt.calibration import apply_transform
from fae.adapt.errors import compatible_closest_points, surface
from fae.adapt.geometry import per_vertex_normals
from fae.adapt.multilevel import METHODS, fit_template
from fae.adapt.synthetic import template_scan
from fae.adapt.transfer import adapt_facemodel, scan_landmarks_in_face_frame, visible_skin
from fae.anatomy.template import TEMPLATE_PATH
from fae.io.facemodel_gltf import read_facemodel


def truth_rms(X, F, scan, T, seen):
    """RMS distance (m) from the fitted vertices `seen` to the clean true surface."""
    Y = apply_transform(np.linalg.inv(scan.to_scan) @ np.linalg.inv(T), X)
    truth = surface(scan.truth_vertices, scan.truth_faces)
    _, _, d, ok = compatible_closest_points(Y, per_vertex_normals(Y, F), truth, 0.01)
    ok &= seen
    return float(np.sqrt(np.mean(d[ok] ** 2)))


def compare_feature_searches(seeds=(4, 5, 6)) -> None:
    """Automatic feature points (fae.adapt.auto_landmarks) on face scans of three synthetic
    people (turned up to 57 degrees, mm): the aligned template's points alone, refined by
    the template fit, and by paper 003's GA; error against the true points, seconds."""
    from fae.adapt.auto_landmarks import auto_landmarks

    model = read_facemodel(TEMPLATE_PATH)
    V, F = model.skin_vertices, model.skin_faces.astype(np.int64)
    seen = visible_skin(model)
    lm = {n: p for n, p in model.feature_point_positions().items() if model.feature_points[n].part == "skin"}
    print(f"{'search':10s} {'seconds':>8s} {'median mm':>10s} {'RMS mm':>8s} {'nose tip mm':>12s}")
    for label, method, rounds in (("aligned", "fit", 0), ("fit", "fit", 2), ("ga", "ga", 0)):
        times, errs, nose = [], [], []
        for seed in seeds:
            scan = template_scan(V, F, lm, seed=seed, subdivisions=1, drop_faces=~seen[F].all(axis=1),
                                 face_only=True, max_angle=1.0)
            t = time.perf_counter()
            found, _ = auto_landmarks(model, scan.vertices, scan.faces, method=method, rounds=rounds)
            times.append(time.perf_counter() - t)
            errs += [np.linalg.norm(found[n] - scan.landmarks[n]) for n in found]
            nose.append(np.linalg.norm(found["9.3"] - scan.landmarks["9.3"]))
        errs = np.array(errs)
        print(f"{label:10s} {np.mean(times):8.2f} {np.median(errs):10.2f} {np.sqrt(np.mean(errs**2)):8.2f} "
              f"{np.mean(nose):12.2f}")


def timed(run, repeat: int):
    """The median wall-clock seconds of `repeat` calls of run() and the last result."""
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--subdivisions", type=int, default=2, help="Loop steps of the scan (2: about 72k vertices)")
    ap.add_argument("--nricp", action="store_true", help="also run trimesh nricp_amberg (about 15 minutes)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per method; the median counts")
    ap.add_argument("--auto", action="store_true", help="only compare the automatic feature point searches")
    args = ap.parse_args()
    if args.auto:
        compare_feature_searches()
        return
    model = read_facemodel(TEMPLATE_PATH)
    V, F = model.skin_vertices, model.skin_faces.astype(np.int64)
    seen = visible_skin(model)
    lm = {n: p for n, p in model.feature_point_positions().items() if model.feature_points[n].part == "skin"}
    scan = template_scan(V, F, lm, seed=11, subdivisions=args.subdivisions, drop_faces=~seen[F].all(axis=1),
                         face_only=True, noise=0.0001, holes=3)
    print(f"template {len(V)} vertices, scan {len(scan.vertices)} vertices; median of {args.repeat} runs")
    T, unit, names, ignored, _ = scan_landmarks_in_face_frame(lm, scan.landmarks, scan.vertices, scan.faces)
    SV = apply_transform(T, scan.vertices)
    PL = np.array([lm[n] for n in names])
    QL = apply_transform(T, np.array([scan.landmarks[n] for n in names]))
    adapt_facemodel(model, scan.vertices, scan.faces, scan.landmarks)  # warm-up (Warp kernels)
    rows = []
    # what `fae adapt` does before writing the head: calibration, fit, transfer of the anatomy
    dt, (head, report) = timed(lambda: adapt_facemodel(model, scan.vertices, scan.faces, scan.landmarks), args.repeat)
    rows.append(("fae adapt", dt, truth_rms(head.skin_vertices, F, scan, np.linalg.inv(head.scan_transform), seen),
                 report["final"]["marker_error"]))
    variants = [(m, 2) for m in METHODS] + [("multilevel", 1), ("multilevel", 0)]
    for method, levels in variants:  # the skin fit alone, on the calibrated scan
        dt, fit = timed(lambda: fit_template(V, F, PL, SV, scan.faces, QL, method=method, levels=levels,
                                             movable=seen), args.repeat)
        label = method if method != "multilevel" else f"multilevel/{levels}"
        rows.append((label, dt, truth_rms(fit.vertices, F, scan, T, seen), fit.final["marker_error"]))
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
        rows.append(("nricp_amberg", dt, truth_rms(X, F, scan, T, seen), me))
    base = rows[-1] if args.nricp else None
    print(f"{'method':14s} {'seconds':>8s} {'truth RMS mm':>13s} {'marker mm':>10s}"
          + ("  speed-up  error ratio" if base else ""))
    for name, dt, err, me in rows:
        extra = f"  {base[1] / dt:8.1f}x {err / base[2]:10.2f}" if base else ""
        print(f"{name:14s} {dt:8.2f} {err * 1000:13.4f} {me * 1000:10.4f}{extra}")


if __name__ == "__main__":
    main()
