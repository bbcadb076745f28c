"""Independent fakes of devices, written from published protocol facts only (never from
cellcal's own twins or drivers), so that a driver is proven against something its authors
did not write."""
