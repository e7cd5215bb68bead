"""A method's identity: MethodSpec, the option table every command and config reads, the protocol presets."""
