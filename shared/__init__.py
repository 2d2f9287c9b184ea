"""telesurg shared library: messages, keys, bus, kinematics, config — imported by every service."""
