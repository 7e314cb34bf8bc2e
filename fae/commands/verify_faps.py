"""`fae verify-faps [HEAD.glb] [--json] [--faps LIST]`: how far each FAP moves its feature point.

Each feature-point-bound low-level FAP is held alone at half its range (half the positive
limit the Player clamps to: the standard's I range in FAPU units) until the skin settles;
the feature point's motion is compared with the standard's (value x FAPU along the FAP's
direction). A FAP passes when the motion along that direction is within 15 % of it.
Exit status 0 when at least 90 % pass, 1 when fewer do, 2 when the head cannot be read or
the FAP list is invalid. Without HEAD the shipped generic head is checked.
"""

from __future__ import annotations

import sys

from fae.commands.common import fail, json_text, load_head

PASS_FRACTION = 0.9


def register(subparsers) -> None:
    parser = subparsers.add_parser("verify-faps", help="check each FAP's feature-point motion on a head",
                                   description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    parser.add_argument("head", nargs="?", default=None, help="FaceModel .glb (default: the generic head)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--faps", default=None, help="comma-separated FAP numbers, ranges or names, e.g. 3,19-22,open_jaw")
    parser.set_defaults(func=run)


def parse_fap_list(text: str) -> list[int]:
    """FAP numbers from '3,19-22,open_jaw', each once and in order: numbers, ranges or the
    standard's names (ValueError naming the bad item: a number outside 1..68, a range
    backwards, a name no FAP has)."""
    from fae.mpeg4.faps import FAP_COUNT, fap_by_name

    out: set[int] = set()
    for item in text.split(","):
        item = item.strip()
        try:
            if not item.isascii():  # int() reads other scripts' digits too
                raise ValueError
            if item and not item[0].isdigit():
                a = b = fap_by_name(item).number
            else:
                a, b = (int(x) for x in item.split("-", 1)) if "-" in item else (int(item),) * 2
            if not 1 <= a <= b <= FAP_COUNT:
                raise ValueError
        except (KeyError, ValueError):
            raise ValueError(f"--faps: expected FAP numbers (1-{FAP_COUNT}), ranges like 3,19-22 or FAP names; "
                             f"got {item!r}, which is neither a FAP number nor a FAP's name") from None
        out.update(range(a, b + 1))
    return sorted(out)


def run(args) -> int:
    from fae.io.facemodel_gltf import FaceModelError

    try:
        faps = parse_fap_list(args.faps) if args.faps is not None else None  # "" is a mistake, not "all"
    except ValueError as exc:
        return fail("verify-faps", str(exc))
    try:
        face, head = load_head(args.head)
    except FaceModelError as exc:
        return fail("verify-faps", str(exc))
    path = str(head)

    import contextlib

    with contextlib.redirect_stdout(sys.stderr):  # Warp's banner and kernel-load lines: stdout is the report's
        from fae.animate.player import Player, playable_head
        from fae.animate.verify import TOLERANCE, passed_fraction, verify_faps

        try:
            player = Player(playable_head(face))
        except (RuntimeError, ValueError) as exc:  # data the engine cannot use (fae template check says which)
            return fail("verify-faps", f"{head}: cannot animate it: {exc}")
        try:
            report = verify_faps(player, faps)
        except ValueError as exc:
            return fail("verify-faps", str(exc))
    fraction = passed_fraction(report)
    if args.json:
        print(json_text({"head": path, "tolerance": TOLERANCE, "faps": report, "passed_fraction": fraction}, indent=1))
    else:
        print(f"{path}: each FAP alone at half its range, settled; ratio = measured / expected along its direction")
        print(f"{'FAP':>4} {'name':<24} {'FDP':<5} {'value':>7} {'expected mm':>12} {'measured mm':>12} {'ratio':>6}")
        for r in report:
            e = sum(x * x for x in r["expected_m"]) ** 0.5 * 1e3
            m = sum(x * x for x in r["measured_m"]) ** 0.5 * 1e3
            print(f"{r['fap']:>4} {r['name']:<24} {r['feature_point']:<5} {r['value']:>7.0f} {e:>12.2f} {m:>12.2f} "
                  f"{r['ratio']:>6.2f}{'' if r['ok'] else '  FAIL'}")
        print(f"passed {sum(r['ok'] for r in report)}/{len(report)} ({100 * fraction:.0f} %) within "
              f"+-{100 * TOLERANCE:.0f} %")
    return 0 if fraction >= PASS_FRACTION else 1
