"""The link to the device: the client end of the protocol, the device programs the host
starts, and the box's local socket endpoint."""
