"""`fae template build [-o FILE]` and `fae template check FILE [--json]`.

build  writes the generic head (default: fae/data/generic_head.glb, the file `fae` plays
       when no head is given: fae.data.shipped_head_path), with its FAP mapping calibrated
       (fae.animate.calibrate) so that players load it at once; the same builder
       tools/build_template.py runs.
check  validates any FaceModel file: structure (fae.io.facemodel_gltf) and geometry
       (fae.anatomy.checks). Exit 0 when valid, 1 when it has problems, 2 when the file
       cannot be read.
"""

from __future__ import annotations


from fae.commands.common import fail, json_text, os_error_text, output_problem


def register(subparsers) -> None:
    parser = subparsers.add_parser("template", help="build the generic head or check a FaceModel file",
                                   description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    sub = parser.add_subparsers(dest="template_command", metavar="ACTION")
    build = sub.add_parser("build", help="build the generic head (.glb)")
    build.add_argument("-o", "--output", default=None,
                       help="output .glb (default: the shipped head, fae/data/generic_head.glb)")
    build.set_defaults(func=run)
    check = sub.add_parser("check", help="validate a FaceModel .glb")
    check.add_argument("file", help="FaceModel .glb to check")
    check.add_argument("--json", action="store_true", help="print a JSON report on stdout")
    check.set_defaults(func=run)
    parser.set_defaults(func=run)


def run(args) -> int:
    action = getattr(args, "template_command", None)
    if action == "build":
        return _build(args.output)
    if action == "check":
        return _check(args.file, args.json)
    return fail("template", "expected an action: build or check (see fae template --help)")


def _build(output: str | None) -> int:
    from fae.anatomy.template import build_template
    from fae.animate.calibrate import calibrate
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import write_facemodel

    path = output or str(shipped_head_path())
    problem = output_problem(path, ".glb")  # before a minute of work, not after it
    if problem:
        return fail("template build", problem)
    model = calibrate(build_template(), early_stop=False)  # a mapping that small changes move a little
    try:
        write_facemodel(model, path)
    except OSError as exc:
        return fail("template build", os_error_text(exc))
    print(f"wrote {path}: {model.skin_vertex_count} skin vertices, {len(model.muscles)} muscles, "
          f"{len(model.feature_points)} feature points")
    return 0


def _check(path: str, as_json: bool) -> int:
    from fae.io.facemodel_gltf import read_facemodel

    try:
        model = read_facemodel(path, check=False)
    except (OSError, ValueError, KeyError) as exc:
        return fail("template check", f"cannot read {path}: {exc}")
    from fae.anatomy.checks import check_report

    report = check_report(model)
    from fae.sim.build import DEFAULTS, checked_params

    try:  # what the simulation would refuse (a count of a billion rings, a stiffness of 1e300)
        checked_params({**DEFAULTS, **{k: v for k, v in (model.layer_params or {}).items() if k in DEFAULTS}})
    except ValueError as exc:
        report["problems"].append(str(exc))
    if as_json:
        print(json_text(report, indent=1))
    else:
        f = report["fapu0"]
        print(f"{path}: {report['skin_vertex_count']} skin vertices, {len(report['muscles'])} muscles, "
              f"parts {', '.join(report['parts'])}")
        if f:
            print("FAPU0 (mm): " + ", ".join(f"{k} {v * 1e3:.2f}" for k, v in f.items()))
        for problem in report["problems"]:
            print(f"problem: {problem}")
        print("valid" if not report["problems"] else f"{len(report['problems'])} problems")
    return 0 if not report["problems"] else 1
