"""Pure numerics: numpy arrays in, frozen dataclasses out. No devices, no SQL, no files."""
