"""The cell's zenoh bus: jobs in, replies, progress and state out.

- :mod:`celld.bus.schema`: the JSON Schema of every message (as data), and the
  validator that turns request bytes into frozen job values.
- :mod:`celld.bus.checker`: the small JSON Schema checker behind it.
- :mod:`celld.bus.keys`: key expressions under ``<prefix>/<cell>/``, and the key table.
- :mod:`celld.bus.security`: who asks (a :class:`~celld.bus.security.Caller`
  per bus user, verified through per-user keys and zenoh's ACL), what each
  role may do, warnings about a bus open to the network.
- :mod:`celld.bus.asyncapi`: the AsyncAPI 2.6 document of the bus, and the
  export of the bundle (the schemas and the document, ``celld bus schema``).
- :mod:`celld.bus.session`: zenoh configs from :class:`~celld.config.BusConfig`
  (modes, endpoints, scouting, user/password, ACL roles) and opening sessions.
- :mod:`celld.bus.server`: :class:`~celld.bus.server.BusServer`, the queryables,
  publications and liveliness token of one cell; the daemon's handler interface.
- :mod:`celld.bus.client`: :class:`~celld.bus.client.CellClient` and
  :func:`~celld.bus.client.discover_cells`.
- :mod:`celld.bus.cli`: ``celld submit | status | jobs | result | cancel | accept | bus schema``.
"""
