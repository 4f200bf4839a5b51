"""The CAN side: the MCB protocol codec, python-can access (recording, replay), the simulated MDS bus.

May import: ``mds_ach.ach`` nothing else of the package (it sits below robot, nodes and tools).
"""
