"""The bus: a Zenoh session with typed publishers, subscribers and queries (:mod:`.session`), each
host's bus options (:mod:`.hosts`), and the router's logins, key ownership and TLS (:mod:`.security`)."""
