"""SocketCAN error-frame bits (``linux/can/error.h``), defined once for the daemon, the simulated bus and tests.

An error frame carries the error class in its CAN id and details in its data bytes; controller states
(``CAN_ERR_CRTL``) are in ``data[1]``.

Imports: nothing (constants only).
"""

from __future__ import annotations

# error class (the CAN id of an error frame)
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100

# controller state, data[1] of a CAN_ERR_CRTL frame
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40  # recovered to error-active
CAN_ERR_CRTL_WARNING = CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING
CAN_ERR_CRTL_PASSIVE = CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE
