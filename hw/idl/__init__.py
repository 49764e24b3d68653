"""Package data: the OMG IDL of the Go2 messages (``unitree_go.idl``)."""
