"""FIROS's modules, one job each (see docs/FIROS.md): configuration, whitelist, robot discovery, topics,
message conversion, NGSI encoding and clients, broker subscriptions, the RCM bridge and the HTTP server."""
