"""What every node shares: QoS profiles, message conversion, parameters, start-up, diagnostics."""
