"""The live gateway (``cncgw run``), all of it: from a committed window to the CNC, OPC UA and MQTT.

Modules, lowest first (each imports only those above it in this list; nothing outside this package but
the commands imports it, ``tests/test_layers.py`` checks):

- :mod:`~gateway.live.audit`: the audit log and the alarms;
- :mod:`~gateway.live.cnc`: the CNC's compensation registers, a Modbus TCP driver with writes;
- :mod:`~gateway.live.plausibility`: the bounds an estimate must meet before it moves an offset;
- :mod:`~gateway.live.tracking`: the estimate stepped per window, gaps filled, rebuilt from the records;
- :mod:`~gateway.live.probes`: the CNC's probes read, stored and applied to the estimate (``[probes]``);
- :mod:`~gateway.live.compensation`: the compensation writer (limits, read-back, heartbeat, audit);
- :mod:`~gateway.live.opcua_server`, :mod:`~gateway.live.outputs` (MQTT): what clients read;
- :mod:`~gateway.live.runtime`: :class:`~gateway.live.runtime.LiveGateway`, which wires them together.

The profile sections these read (``[live]``, ``[compensation]``, ``[opcua]``, ``[mqtt]``, ``[probes]``,
``[records]``) are parsed on the profile's side (:mod:`gateway.profile`); the records store, the sampler
and the model are below.
"""
