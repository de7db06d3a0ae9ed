"""Packaged configurations (`thermod.configs`): sim.toml (the embedded default) and hardware examples."""
