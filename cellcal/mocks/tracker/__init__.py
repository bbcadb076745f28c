"""The laser tracker twin: the line protocol's server and one client's session."""
