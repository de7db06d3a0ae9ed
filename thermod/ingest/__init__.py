"""Recordings from other tools → format v1: a ROS recording (`bag`), a thermal video with a
flight-controller log, synced (`flight`), and a thermal video alone, its gyro estimated from the
pictures (`video_only`). Each ingest reads through `thermod.io`, places the data on one clock and
writes a recording whose attributes say where every part came from."""
