"""The arena's plain data, with no I/O: errors, key names, the typed wire payloads, the config.

Everything else builds on these: :mod:`~arena_common.core.keys` names every Zenoh key,
:mod:`~arena_common.core.wire` defines each payload (msgspec Structs, msgpack with short field names),
:mod:`~arena_common.core.config` reads and checks an arena config, :mod:`~arena_common.core.errors` is the
small exception hierarchy every layer raises, :mod:`~arena_common.core.waiting` the one bounded wait for a
condition.
"""
