"""The NGSI versions FIROS speaks, by the name `config.json`'s `ngsi_version` gives them: the one place where the
version is chosen. Every other module talks to whichever client `client_for` made.
"""

from include.ngsi_ld import NgsiLdClient
from include.ngsi_v1 import NgsiV1Client
from include.ngsi_v2 import NgsiV2Client

CLIENTS = {"v1": NgsiV1Client, "v2": NgsiV2Client, "ld": NgsiLdClient}


def client_for(settings, timeout=5.0, observer=None):
    """A new client (its own connection) speaking the configured ``settings.ngsi_version``; ``observer`` is told of
    each of its requests (see ``NgsiClient``)."""
    return CLIENTS[settings.ngsi_version](settings, timeout, observer)
