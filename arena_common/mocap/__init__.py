"""Motion capture in: the NatNet codec (:mod:`.natnet`), a NatNet client with Motive's clock mapped onto
ours (:mod:`.client`), the mocap sources ingest can read (:mod:`.sources`), and pcap/JSON captures
(:mod:`.capture`).  **Where a pose is decoded**: :mod:`.natnet` (``decode_frame``)."""
