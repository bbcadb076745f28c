"""The Modbus TCP robot twin: the MBAP framing, the register map's state and the server."""
