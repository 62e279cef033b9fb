"""The cell's zenoh bus: jobs in, replies, progress and state out.

- :mod:`celld.bus.messages`: the JSON Schema of every message (as data) and the
  bundle they make with what others build (each job kind's result, the
  calibrations: :data:`celld.daemon.results.BUNDLE`).
- :mod:`celld.bus.requests`: the requests as frozen values, built from checked
  messages; a job back to its message.
- :mod:`celld.bus.wire`: a message's bytes: the hostile-JSON loader, the
  encoder, the error reply.
- :mod:`celld.bus.checker`: the small JSON Schema checker behind them.
- :mod:`celld.bus.keys`: key expressions under ``<prefix>/<cell>/``, and the key table.
- :mod:`celld.bus.security`: who asks (a :class:`~celld.bus.security.Caller`
  per bus user, verified through per-user keys and zenoh's ACL), what each
  role may do, warnings about a bus open to the network.
- :mod:`celld.bus.asyncapi`: the AsyncAPI 2.6 document of the bus, and the
  export of a bundle (the schemas and the document; ``celld bus schema``, the
  daemon's command, exports the cell's).
- :mod:`celld.bus.session`: zenoh configs from :class:`~celld.config.BusConfig`
  (modes, endpoints, scouting, user/password, ACL roles) and opening sessions.
- :mod:`celld.bus.server`: :class:`~celld.bus.server.BusServer`, the queryables,
  publications and liveliness token of one cell; the daemon's handler interface.
- :mod:`celld.bus.client`: :class:`~celld.bus.client.CellClient` and
  :func:`~celld.bus.client.discover_cells`.
- :mod:`celld.bus.cli`: ``celld submit | status | jobs | result | cancel | accept | robot``.
"""
