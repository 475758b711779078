"""``python -m holowarp.poses IMAGES --masks MASKS --out DIR``: camera poses from photos.

Thin command over :func:`holowarp.data.sfm.run_sfm`: pycolmap's structure from motion on the
CPU (SIFT features, exhaustive matching, incremental mapping) writes the COLMAP folder
``DIR/sparse/0`` + ``DIR/images`` + ``DIR/masks`` that every holowarp command reads as a
dataset (``python -m holowarp.reconstruct DIR``).
"""

from __future__ import annotations

import json
import sys

from holowarp import cli

__all__ = ["main", "build_parser"]


def build_parser():
    from holowarp.data.common import IMAGE_EXTS
    from holowarp.data.sfm import CAMERA_MODELS, SfMSettings

    d = SfMSettings()
    p = cli.parser(
        "holowarp.poses",
        "Camera poses from photos of one object: structure from motion (pycolmap, CPU) writes a COLMAP folder "
        "(DIR/sparse/0, DIR/images, DIR/masks) that holowarp loads as a dataset.",
        epilog="Photos: " + ", ".join(IMAGE_EXTS) + " files in IMAGES (subfolders too), at least 3, all one size "
               "unless --camera-per-image. Masks: one per photo in MASKS, matched by file stem (masks/a.png or "
               "masks/a.jpg.png for images/a.jpg), white = object. Exit status 2 for unusable input, 1 when too "
               "few photos could be posed.")
    p.add_argument("images", metavar="IMAGES", help="folder of photos")
    p.add_argument("--masks", required=True, metavar="MASKS", help="folder of foreground masks, matched to photos by file stem")
    p.add_argument("--out", required=True, metavar="DIR", help="COLMAP folder to write")
    p.add_argument("--camera-model", default=d.camera_model, choices=CAMERA_MODELS,
                   help=f"camera model to estimate (default {d.camera_model}; the radial models are undistorted on load)")
    p.add_argument("--camera-per-image", action="store_true",
                   help="estimate one camera per photo (default: one shared camera, as for one camera at fixed zoom)")
    p.add_argument("--max-features", type=int, default=d.max_features, metavar="N",
                   help=f"SIFT features per photo (default {d.max_features}, >= 1)")
    p.add_argument("--mask-features", action="store_true",
                   help="use only features inside the masks (turntable captures, where the background does not move with the object)")
    p.add_argument("--min-registered", type=float, default=d.min_registered, metavar="F",
                   help=f"fail unless this fraction of the photos is posed (default {d.min_registered}, in (0, 1])")
    p.add_argument("--seed", type=int, default=d.seed, help=f"random seed (default {d.seed})")
    # dest differs from the common --threads so cli.run does not read COLMAP's -1 ("all cores") as holowarp's.
    p.add_argument("--threads", dest="sfm_threads", type=int, default=d.threads, metavar="N",
                   help="CPU threads for COLMAP (default -1: all cores)")
    p.add_argument("--overwrite", action="store_true", help="replace a COLMAP model already in DIR")
    cli.add_device(p, note="accepted for the common convention; structure from motion always runs on the CPU",
                   threads=False)
    cli.add_quiet(p)
    return p


def _run(args) -> int:
    from holowarp.data.sfm import SfMSettings, run_sfm
    from holowarp.device import resolve_device

    resolve_device(args.device)
    settings = SfMSettings(camera_model=args.camera_model, single_camera=not args.camera_per_image,
                           max_features=args.max_features, mask_features=args.mask_features,
                           min_registered=args.min_registered, seed=args.seed, threads=args.sfm_threads)
    summary = run_sfm(args.images, args.masks, args.out, settings=settings, overwrite=args.overwrite,
                      progress=not args.quiet)
    print(json.dumps({k: summary[k] for k in ("photos", "registered", "unregistered", "points3D",
                                              "mean_reprojection_error_px", "model")}, indent=2))
    return 0


def main(argv=None) -> int:
    return cli.run(_run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
