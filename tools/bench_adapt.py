"""Benchmark of fae's fitting methods against trimesh's non-rigid ICP (nricp_amberg).

Template: the shipped generic head's skin (about 9,000 vertices). Scan: another person made
from it (fae.adapt.synthetic.template_scan): warped by a smooth random field plus fine
detail, remeshed by two Loop steps (about 72k vertices on the face), without the parts no
scanner sees (inside of the mouth, lip slit, eye sockets), with noise and holes, in
millimetres and turned. All methods get the same feature points; nricp gets the
calibrated scan and the landmark pairs. Rows: "fae adapt" is everything
`fae adapt --method multilevel --landmarks` does before writing the head (calibration of
pose and unit, the multilevel fit, transfer of skull, jaw, muscles, eyes, teeth and
tongue; not the FAP mapping), the method rows are the skin fit alone on the calibrated
scan. Prints the median seconds of
--repeat runs, RMS distance of the visible template vertices to the true surface, marker
error, and ratios against nricp measured in the same run. Single-threaded BLAS is
advised for comparable numbers:

    OMP_NUM_THREADS=1 .venv/bin/python tools/bench_adapt.py [--nricp] [--subdivisions 2] [--repeat 3]
    OMP_NUM_THREADS=1 .venv/bin/python tools/bench_adapt.py --auto    (feature point searches)
    OMP_NUM_THREADS=1 .venv/bin/python tools/bench_adapt.py --real [--nricp]    (real scans)

--real runs `fae adapt`'s default pipeline ("surface": the head found in the scan, points
matched by MediaPipe, the fit without folds, the anatomy carried over) on whole busts:
the synthetic bust the tests use (fae.adapt.synthetic.bust_scan, seed 3) and the three
scanned busts of shared/data/heads/busts when that folder is there. Beside it: "old
default", what `fae adapt` did before (feature points guessed by fae.adapt.auto_landmarks,
paper 000's multilevel fit on the whole scan), and with --nricp trimesh's nricp_amberg
fitting the template skin to the same head part with the surface pipeline's MediaPipe
pairs as landmarks. Every row is measured alike, in the scan's own frame against the head
part the surface pipeline cut out (fae.adapt.errors.scan_fit_errors over the face skin
adapt_to_scan scores; folds by fae.adapt.nonrigid.folded_triangles), so the old default
is not judged on the plinth it was fitted to. One run each; seconds exclude the imports and first
Warp / GL / MediaPipe start-up, made once before the first scan. --real takes a few
minutes; --nricp adds about a minute per scan.
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
from fae.data import shipped_head_path
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

    model = read_facemodel(shipped_head_path())
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


# nricp_amberg's default steps [smoothness, landmark weight, normal weight, iterations],
# except that the last keeps the landmarks at the third step's weight: trimesh drops them
# there (0), and the lips and lids then slide off their MediaPipe points.
NRICP_STEPS = [[0.01, 10, 0.5, 10], [0.02, 5, 0.5, 10], [0.03, 2.5, 0.5, 10], [0.01, 2.5, 0.0, 10]]
REAL_BUSTS = ("marble_bust", "man_with_wreath", "demosthenes")


def real_scans(template) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, V, F) of the scans of --real: the tests' synthetic bust (mm, turned), then
    the scanned busts of shared/data when present."""
    from pathlib import Path

    from fae.adapt.synthetic import template_bust
    from fae.io.scan import read_scan

    bust = template_bust(template)
    scans = [("synthetic bust", bust.vertices, bust.faces)]
    data = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    if not data.is_dir():
        print(f"note: {data} not found; the scanned busts are left out")
        return scans
    for name in REAL_BUSTS:
        V, F = read_scan(data / "heads" / "busts" / name / f"{name}.obj")
        scans.append((name, V, F))
    return scans


def scored_skin(template) -> tuple[np.ndarray, np.ndarray]:
    """(face (n,) bool, seen (n,) bool): the skin adapt_to_scan scores, so that every row
    is judged like the surface pipeline's own report: the face regions a scanner sees,
    less the lids' rims over the eyeballs."""
    from fae.adapt.errors import FACE_REGIONS
    from fae.adapt.from_scan import EYE_RIM, in_regions, near_eyeballs

    seen = visible_skin(template) & ~near_eyeballs(template, EYE_RIM)
    return in_regions(template, FACE_REGIONS) & seen, seen


def measured(template, X, S, scan_part, face, seen) -> dict:
    """Errors and folds of a fitted skin X (n, 3) in the face frame, metres, that S (4, 4)
    maps into the scan's frame and unit: scan_fit_errors there against the head part
    (V, F, scan frame), folds in the face frame against the template."""
    from fae.adapt.errors import scan_fit_errors
    from fae.adapt.from_scan import in_regions
    from fae.adapt.nonrigid import folded_triangles

    F = np.asarray(template.skin_faces, dtype=np.int64)
    errors = scan_fit_errors(apply_transform(S, X), F, face, scan_part[0], scan_part[1],
                             neck=in_regions(template, ["neck"]))
    folded = folded_triangles(template.skin_vertices, X, F)
    return {"errors": errors, "folded": (int(folded[seen[F].all(axis=1)].sum()), int(folded.sum()))}


def surface_run(template, V, F) -> dict:
    """`fae adapt`'s default pipeline on one scan, phase by phase (perf_counter seconds)."""
    from fae.adapt.from_scan import adapt_to_scan
    from fae.adapt.head_pose import find_head, kept_part
    from fae.render.framing import camera_view
    from fae.render.landmarks import landmark_pairs

    t0 = time.perf_counter()
    head = find_head(template, V, F)
    t1 = time.perf_counter()
    part_V, part_F = kept_part(apply_transform(head.transform, V), F, head.keep)
    found = landmark_pairs(template, part_V, part_F, camera_view(template, "front", aspect=1.0),
                           seen=visible_skin(template))
    t2 = time.perf_counter()
    # as `fae adapt` does: fewer than 20 pairs are no face (the CLI stops there; here the fit goes on)
    pairs = (found.face, found.bary, found.scan_points) if found is not None and len(found.face) >= 20 else None
    model, report = adapt_to_scan(template, V, F, head, pairs, None)
    t3 = time.perf_counter()
    return {"head": head, "part": (part_V, part_F), "pairs": pairs, "model": model, "report": report,
            "phases": {"find_head": t1 - t0, "landmark_pairs": t2 - t1, "adapt_to_scan": t3 - t2},
            "seconds": t3 - t0, "fit_seconds": report["fit_seconds"]}


def old_default_run(template, V, F) -> dict:
    """What `fae adapt` did before: feature points guessed by ICP, the multilevel fit."""
    from fae.adapt.auto_landmarks import auto_landmarks

    t0 = time.perf_counter()
    lm, _ = auto_landmarks(template, V, F, method="fit")
    model, report = adapt_facemodel(template, V, F, lm, method="multilevel", levels=1)
    # fit_template's clock at its last level (adapt_facemodel's own total includes the transfer)
    return {"model": model, "seconds": time.perf_counter() - t0, "fit_seconds": report["levels"][-1]["seconds"]}


def nricp_run(template, part_V, part_F, pairs) -> tuple[np.ndarray, float]:
    """trimesh's nricp_amberg: the template skin, as shipped (face frame, like the head
    part), fitted to the head part with the MediaPipe pairs as its landmarks; the fitted
    vertices (face frame) and seconds."""
    import trimesh

    src = trimesh.Trimesh(template.skin_vertices, np.asarray(template.skin_faces, np.int64), process=False)
    tgt = trimesh.Trimesh(part_V, part_F, process=False)
    t = time.perf_counter()
    X = trimesh.registration.nricp_amberg(src, tgt, source_landmarks=(np.asarray(pairs[0], np.int64), pairs[1]),
                                          target_positions=pairs[2], steps=NRICP_STEPS)
    return np.asarray(X, dtype=np.float64), time.perf_counter() - t


def warm_up(template) -> None:
    """Imports, Warp kernels, a GL context and MediaPipe once, so the first scan's
    seconds are like the others'."""
    from fae.render.framing import camera_view
    from fae.render.landmarks import face_points_seen

    face_points_seen(template, camera_view(template, "front", aspect=1.0))
    face, _ = scored_skin(template)
    from fae.adapt.errors import scan_fit_errors

    scan_fit_errors(template.skin_vertices, template.skin_faces, face, template.skin_vertices, template.skin_faces)


def compare_real_scans(nricp: bool) -> None:
    """The table of --real (see the module docstring)."""
    from fae.adapt.head_pose import kept_part

    template = read_facemodel(shipped_head_path())
    face, seen = scored_skin(template)
    scans = real_scans(template)
    warm_up(template)
    rows, notes, ratios = [], [], []
    for name, V, F in scans:
        print(f"{name}: {len(V)} vertices, {len(F)} triangles", flush=True)
        try:
            run = surface_run(template, V, F)
        except Exception as exc:  # a scan the pipeline cannot take is a result too
            notes.append(f"{name}: fae surface failed: {type(exc).__name__}: {exc}")
            continue
        head = run["head"]
        scan_part = kept_part(V, F, head.keep)  # the head part, in the scan's own frame
        ph = run["phases"]
        print(f"  fae surface: find_head {ph['find_head']:.1f} s, landmark_pairs {ph['landmark_pairs']:.1f} s, "
              f"adapt_to_scan {ph['adapt_to_scan']:.1f} s (fit {run['fit_seconds']:.1f} s); "
              f"{0 if run['pairs'] is None else len(run['pairs'][0])} pairs", flush=True)
        surface = measured(template, run["model"].skin_vertices, run["model"].scan_transform, scan_part, face, seen)
        rows.append((name, "fae surface", run["seconds"], run["fit_seconds"], surface))
        try:
            old = old_default_run(template, V, F)
            m = measured(template, old["model"].skin_vertices, old["model"].scan_transform, scan_part, face, seen)
            rows.append((name, "old default", old["seconds"], old["fit_seconds"], m))
            ratios.append(f"{name}: fae surface vs old default: face RMS "
                          f"{surface['errors']['face_to_scan_rms_rel'] / m['errors']['face_to_scan_rms_rel']:.2f}x, "
                          f"seconds {run['seconds'] / old['seconds']:.2f}x")
        except Exception as exc:
            notes.append(f"{name}: old default failed: {type(exc).__name__}: {exc}")
        if nricp:
            if run["pairs"] is None:
                notes.append(f"{name}: trimesh nricp left out: no MediaPipe pairs to give it")
                continue
            try:
                X, dt = nricp_run(template, *run["part"], run["pairs"])
                m = measured(template, X, np.linalg.inv(head.transform), scan_part, face, seen)
                rows.append((name, "trimesh nricp", dt, dt, m))
                print(f"  trimesh nricp: {dt:.1f} s", flush=True)
            except Exception as exc:
                notes.append(f"{name}: trimesh nricp failed: {type(exc).__name__}: {exc}")
    print()
    print(f"{'scan':16s} {'row':14s} {'seconds':>8s} {'fit s':>7s} {'face RMS %':>11s} {'face cov %':>11s} "
          f"{'scan RMS %':>11s} {'scan cov %':>11s} {'no neck %':>10s} {'folded vis':>11s} {'folded all':>11s}")
    for name, label, dt, fit_dt, m in rows:
        e = m["errors"]
        fit_s = f"{fit_dt:7.1f}" if fit_dt is not None else f"{'-':>7s}"
        print(f"{name:16s} {label:14s} {dt:8.1f} {fit_s} {e['face_to_scan_rms_rel'] * 100:11.3f} "
              f"{e['face_coverage'] * 100:11.1f} {e['scan_to_skin_rms_rel'] * 100:11.3f} "
              f"{e['scan_coverage'] * 100:11.1f} {e['head_to_skin_rms_rel'] * 100:10.3f} "
              f"{m['folded'][0]:11d} {m['folded'][1]:11d}")
    print("RMS: % of the head part's bounding-box diagonal; coverage: share within 2 % of it; no neck: the scan "
          "-> skin RMS over the scan whose nearest skin is not the neck (cranium, face, ears)")
    for line in ratios + notes:
        print(line)


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
    ap.add_argument("--nricp", action="store_true", help="also run trimesh nricp_amberg (about 15 minutes; "
                    "with --real about a minute per scan)")
    ap.add_argument("--real", action="store_true", help="fae adapt's surface pipeline on whole busts (module docstring)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per method; the median counts")
    ap.add_argument("--auto", action="store_true", help="only compare the automatic feature point searches")
    args = ap.parse_args()
    if args.auto:
        compare_feature_searches()
        return
    if args.real:
        compare_real_scans(args.nricp)
        return
    model = read_facemodel(shipped_head_path())
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
