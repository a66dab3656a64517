"""Command line: `mvcalib demo`, `mvcalib calibrate-images` (also `python -m mvcalib ...`).

Exit codes: 0 success, 1 the work failed (e.g. a camera could not be calibrated), 2 bad usage.

The CLI keeps JAX's persistent compilation cache in `$XDG_CACHE_HOME/mvcalib/jax` (default
`~/.cache/mvcalib/jax`), so that only the first run pays for compiling; set
`MVCALIB_COMPILATION_CACHE=0` to turn it off, or to a directory to put it elsewhere.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys

EXAMPLES = """examples:
  mvcalib demo                    the paper's experiment with 0.3 px noise
  mvcalib demo --noise-free       no noise: the four snapshots agree to 1e-6 px
  mvcalib demo --float32          the same in single precision
  mvcalib demo --images           the whole pipeline from rendered photographs, and a figure
                                  of the detection stages (mvcalib_stages.png)
  mvcalib calibrate-images cam*.png --out rig.json
                                  one camera per photo of the box-corner target
"""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line and exit code 2, no usage dump or traceback
        self.exit(2, f"mvcalib: error: {message} (see `mvcalib --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="mvcalib",
        description="Calibrate rigs of cameras (DLT + SVD, closed-form decomposition, "
        "registration into one global frame).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    demo = sub.add_parser(
        "demo",
        help="run the paper's 4-snapshot experiment on a synthetic scene",
        description="Run the paper's experiment on a synthetic scene: DLT per snapshot, "
        "Table I, registration into the global frame, and the fixed point's pixel from every "
        "snapshot.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument("--noise", type=float, default=0.3, help="pixel noise sigma (default 0.3)")
    demo.add_argument(
        "--global-noise",
        type=float,
        default=0.0,
        help="noise sigma of the measured global coordinates, mm (default 0)",
    )
    demo.add_argument("--noise-free", action="store_true", help="set both noises to zero")
    demo.add_argument("--seed", type=int, default=2010, help="PRNG seed of the scene")
    demo.add_argument("--float32", action="store_true", help="compute in single precision")
    demo.add_argument(
        "--images",
        action="store_true",
        help="start from rendered photographs: detect, label, calibrate, register",
    )
    demo.add_argument(
        "--figure",
        default="mvcalib_stages.png",
        metavar="PNG",
        help="with --images: where to write the processing-stage figure "
        "(default mvcalib_stages.png; '' for none)",
    )

    images = sub.add_parser(
        "calibrate-images",
        help="calibrate one camera per photograph of the dot target",
        description="Detect the dots in each photograph (the paper's morphological steps), "
        "label them from the target's large fiducial dots, and calibrate one camera per image "
        "(DLT, closed-form decomposition, Table I). Images that cannot be labelled with "
        "certainty are flagged, never calibrated wrongly; the rig file records their status.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    images.add_argument("images", nargs="+", metavar="IMG", help="photographs (PNG, TIFF, ...)")
    images.add_argument("--out", required=True, metavar="JSON", help="rig file to write")
    images.add_argument(
        "--refine",
        action="store_true",
        help="refine each camera by Levenberg-Marquardt with radial/tangential distortion",
    )
    images.add_argument(
        "--bright-dots", action="store_true", help="bright dots on a dark background"
    )
    images.add_argument("--quiet", action="store_true", help="no per-image progress lines")
    return parser


def _enable_compilation_cache(jax) -> None:
    setting = os.environ.get("MVCALIB_COMPILATION_CACHE", "")
    if setting == "0":
        return
    if setting:
        path = pathlib.Path(setting)
    else:
        cache = pathlib.Path(os.environ.get("XDG_CACHE_HOME", pathlib.Path.home() / ".cache"))
        path = cache / "mvcalib" / "jax"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: run without the cache rather than fail
        return
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    import jax

    jax.config.update("jax_enable_x64", True)
    _enable_compilation_cache(jax)
    if args.command == "calibrate-images":
        return _calibrate_images(parser, args)
    if args.command == "demo":
        from . import demo

        if args.images:
            return demo.main_images(seed=args.seed, figure=args.figure or None)
        if args.noise < 0 or args.global_noise < 0:
            parser.error("noise levels must be non-negative")
        noise, global_noise = (0.0, 0.0) if args.noise_free else (args.noise, args.global_noise)
        try:
            return demo.main(
                noise=noise, global_noise=global_noise, seed=args.seed, float32=args.float32
            )
        except ValueError as e:  # includes CalibrationError
            print(f"mvcalib: {e}", file=sys.stderr)
            return 1
    return 2


def _calibrate_images(parser, args) -> int:
    missing = [p for p in args.images if not pathlib.Path(p).is_file()]
    if missing:
        parser.error(f"no such image file: {missing[0]}")
    out = pathlib.Path(args.out)
    if not out.parent.is_dir():
        parser.error(f"the folder of --out does not exist: {out.parent}")
    from . import io
    from ._images import calibrate_images

    result = calibrate_images(
        args.images,
        refine=args.refine,
        detect=dict(dark_dots=not args.bright_dots),
        progress=not args.quiet,
    )
    print(result)
    io.save_json(
        out,
        result.cameras,
        names=result.names,
        status=result.calibration.status,
        rms=result.calibration.report.rms,
        meta={"target": "box corner, 19 dots", "messages": result.messages},
    )
    n_ok = int(result.ok.sum())
    print(f"\n{n_ok} of {len(result.names)} cameras calibrated; rig written to {out}")
    return 0 if n_ok == len(result.names) else 1


if __name__ == "__main__":
    sys.exit(main())
