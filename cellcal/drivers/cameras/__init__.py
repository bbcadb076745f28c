"""The camera backends of the photogrammetry rig: aravis (GigE Vision, USB3 Vision), opencv
(UVC, RTSP, HTTP) and files (recorded image sets), chosen by ``backend`` in the rig's
configuration (``backends.py``)."""
