"""The simulated devices served over the real protocols (Modbus TCP, CANopen, serial pty)."""
