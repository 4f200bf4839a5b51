"""Recording and looking back: every channel of a running system to MCAP, plots, replay.

* :mod:`.schema` -- a wire struct as a ROS 2 message (definition, to and from a message), the topic of each channel;
* :mod:`.stream` -- every frame of one channel, in order, as a normal reader (survives channels that vanish);
* :mod:`.sink` -- the MCAP file(s): split by size or time, a clear stop before the disk is full;
* :mod:`.canlog` -- the daemon's CAN frames in a recording (import from its ``--can-log``, back to python-can);
* :mod:`.recording` -- reading a recording back, a cut one (SIGKILL) included;
* :mod:`.recorder` -- ``mds-ach record``; :mod:`.plot` -- ``mds-ach plot``; :mod:`.replay` -- ``mds-ach replay``.

The encoding (ROS 2 ``.msg`` schemas, CDR) is explained in docs/architecture.md ("Recordings").
"""
