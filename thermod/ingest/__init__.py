"""Recordings from other tools → format v1: a ROS recording (`bag`) and a thermal video with a
flight-controller log, synced (`flight`). Each ingest reads through `thermod.io`, places the data on
one clock and writes a recording whose attributes say where every part came from."""
