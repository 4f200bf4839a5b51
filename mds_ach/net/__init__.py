"""Network sharing of channels: the achd wire protocol, server and client, SSH tunnels.

May import: ``ach``, ``robot``.
"""
