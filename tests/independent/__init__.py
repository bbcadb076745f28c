"""Devices written from their published protocols alone, not from cellcal's twins: the
second opinion a twin cannot give."""
