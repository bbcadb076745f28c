"""The photogrammetry numerics (pure): ChArUco board and marker corners, the camera rig's
calibration (bundle adjustment, verdict, views) and the target's measurement."""
