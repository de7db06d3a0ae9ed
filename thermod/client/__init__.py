"""Clients of the daemon's stream: the wire-v1 subscriber and the browser view `thermod watch --web`
serves. They depend on the daemon's transport rules (`thermod.io.endpoints`), never on its
threads; nothing below this package imports it.
"""
