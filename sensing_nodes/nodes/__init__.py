"""One module per executable: parameters, topics, QoS, message <-> array conversion."""
