"""A campaign's life: its plan, its kind (calibration, ISO 9283 test), the one runner that
starts, resumes, pauses and records every kind, the engine that visits the poses, the
record stream, and the analysis at the end."""
