"""Workflow 1 (paper §III-A): photogrammetry capture around a tree and COLMAP reconstruction with pose priors.

* :mod:`.capture` flies a circular capture pattern through the WebSocket API and records RGB frames,
  camera poses (TF) and intrinsics (camera_info) from the ROS 2 topics over Zenoh;
* :mod:`.colmap_model` writes and reads COLMAP text models and holds the pixel-convention conversion;
* :mod:`.reconstruct` runs SIFT (masked to the tree), matching, triangulation from the known poses and
  bundle adjustment with pose priors in pycolmap (optional extra ``droneulator[colmap]``), then
  :mod:`.dense`: COLMAP's CUDA PatchMatch, or on a CPU the plane sweep of :mod:`.mvs` and the fusion of
  :mod:`.fusion`;
* :mod:`.truth` and :mod:`.score` measure the clouds against the true tree the capture recorded.
"""
