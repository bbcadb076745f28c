"""The FANUC controller twin (Remote Motion Interface)."""
