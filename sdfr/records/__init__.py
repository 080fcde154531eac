"""The records both layers and every client share: a robot's services (`model`), the REST
API's JSON (`schema`), the event log's entries (`events`) and the discovery layer's status
(`status`).  No I/O; importing one loads neither the daemon nor the wire codec."""
