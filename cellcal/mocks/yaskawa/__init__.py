"""The Yaskawa controller twin (High-Speed Ethernet Server)."""
