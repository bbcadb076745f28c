"""Device drivers, one module per device family; the Protocols are in ``base``."""
