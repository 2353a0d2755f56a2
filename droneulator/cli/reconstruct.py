"""``droneulator reconstruct``: COLMAP reconstruction of a capture (needs pycolmap)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="COLMAP reconstruction of a capture: SIFT, matching, triangulation from the known poses, "
        "bundle adjustment with pose priors (needs pycolmap: pip install droneulator[colmap])",
    )
    p.add_argument("dataset", help="a folder written by `droneulator capture`")
    p.add_argument("--max-features", type=int, default=8192, help="SIFT features per image")
    p.add_argument(
        "--matcher",
        choices=("spatial", "exhaustive"),
        default="spatial",
        help="spatial: each image with its nearest neighbours by prior position (default); "
        "exhaustive: all pairs",
    )
    p.add_argument("--neighbors", type=int, default=12, help="spatial matcher: neighbours per image")
    p.add_argument(
        "--prior-std", type=float, default=0.01, help="standard deviation of the position priors (m)"
    )
    p.add_argument(
        "--verification",
        choices=("ransac", "known_poses"),
        default="ransac",
        help="two-view verification: COLMAP's RANSAC (homographies not accepted; default) or the matches "
        "that agree with the recorded relative poses",
    )
    p.add_argument(
        "--refine-rotations", action="store_true", help="let bundle adjustment refine the camera rotations"
    )
    p.add_argument(
        "--filter-max-error",
        type=float,
        default=2.0,
        help="after bundle adjustment drop observations with a larger reprojection error (px; default 2)",
    )
    p.add_argument(
        "--filter-min-angle",
        type=float,
        default=1.5,
        help="... then points triangulated at a smaller angle (deg; default 1.5)",
    )
    p.add_argument(
        "--filter-min-track",
        type=int,
        default=None,
        help="... then points seen in fewer images (default: 3 where three views lie within 45 degrees, "
        "as on rings of 16 views or more, else 2; COLMAP's own default, 2, keeps two-view points, which "
        "the tree's mismatches are)",
    )
    p.add_argument("--no-dense", action="store_true", help="skip dense reconstruction")
    p.add_argument(
        "--mask",
        choices=("tree", "none"),
        default="tree",
        help="SIFT on the tree's pixels only (the recorded segmentation; default) or on whole images",
    )
    p.add_argument(
        "--dense-mask",
        choices=("tree", "none"),
        default="tree",
        help="CPU dense stereo on the tree's pixels only (default) or on whole images",
    )
    p.add_argument(
        "--dense-scale",
        type=float,
        default=None,
        help="CPU dense stereo image scale (default: MvsOptions.scale, 0.75)",
    )
    p.add_argument(
        "--cpu-dense", action="store_true", help="the CPU plane sweep even where pycolmap has CUDA"
    )
    p.set_defaults(func=cmd_reconstruct)


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from droneulator.workflows.photogrammetry.dense import DenseOptions
    from droneulator.workflows.photogrammetry.mvs import MvsOptions
    from droneulator.workflows.photogrammetry.reconstruct import ReconstructOptions, reconstruct

    mvs = MvsOptions() if args.dense_scale is None else MvsOptions(scale=args.dense_scale)
    dense = DenseOptions(mvs=mvs, mask=args.dense_mask, path="cpu" if args.cpu_dense else "auto")
    opts = ReconstructOptions(
        mask=args.mask,
        dense_options=dense,
        max_features=args.max_features,
        matcher=args.matcher,
        spatial_neighbors=args.neighbors,
        prior_position_std_m=args.prior_std,
        verification=args.verification,
        refine_rotations=args.refine_rotations,
        filter_max_reproj_error_px=args.filter_max_error,
        filter_min_tri_angle_deg=args.filter_min_angle,
        filter_min_track_length=args.filter_min_track,
        dense=not args.no_dense,
    )
    report = reconstruct(Path(args.dataset), opts)
    return 0 if report["registered_images"] >= 2 else 1
