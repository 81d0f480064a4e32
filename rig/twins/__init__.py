"""Software twins of the rig's devices, served on real ports so drivers run their real code path."""
