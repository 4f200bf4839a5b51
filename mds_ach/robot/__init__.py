"""The robot's description and the channel contracts: joint table (YAML, anatomy XML), robot variants,
wire structs, motion bounds, which channels exist and who may write them.

May import: ``mds_ach.ach``, ``mds_ach.bus``.
"""
