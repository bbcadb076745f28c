"""cellcal.daemon — see DESIGN.md; filled in by later issues."""
