"""The ABB twin: an IRC5 running cellcal's RAPID module behind Robot Web Services."""
