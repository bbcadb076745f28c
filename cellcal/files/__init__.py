"""The files of the public contract, read and written at the edge (the numerics stay free
of files): measurements, points, targets, models, URDF, the rig, target and board,
images, outputs."""
