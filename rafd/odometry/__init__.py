"""Radar odometry: the ego's SE(2) motion between consecutive scans by image registration (opencv + numpy), what the
service runs for a stream posted without poses and `rafd odometry` runs over whole sequences (rafd.data.ego_motion).

- `registration`: the estimator (estimate_relative_pose, OdometryStream for a stream, estimate_sequence_poses) and
  the sweep timing it de-skews with;
- `ecc`: the inverse-compositional ECC that refines its yaw.

Import the submodules."""
