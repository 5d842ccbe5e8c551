"""Commands on platform instances (robots) behind the RDAPI: read, provisioning and r_provisioning.

Each command validates its input (``rcmp_command``), does its SQLite work in a thread (``deferToThread``) and
returns a Deferred firing with the ``reason`` of an OK answer or failing with a ``CommandError``. Removing a
connected robot first asks the master runtime (``robots.disconnect``) to disconnect it and tear its service space
down. Reads are answered from a ``ReadCache`` while the robotics data has not changed.
"""

from twisted.internet import defer, threads

from .rcmp_command import command, ReadCache, require_fields, validate_name


class PlatformCommands:
    """``data``: RoboticsData; ``robots``: object with ``disconnect(pi_name, reason) -> Deferred`` or None."""

    def __init__(self, data, robots=None):
        self.data = data
        self.robots = robots
        self.cache = ReadCache(data)

    @command
    def read(self):
        """The list of provisioned robots (master excluded)."""
        cached = self.cache.get("platform_instances")
        if cached is not None:
            return defer.succeed(cached)
        generation = self.data.generation
        d = threads.deferToThread(self.data.platform_instances)
        d.addCallback(lambda rows: self.cache.put("platform_instances", generation, rows))
        return d

    @command
    def provisioning(self, body):
        """Provision ``pi_name`` with the existing service logic ``pi_service_logic``."""
        require_fields(body, ("pi_name", "pi_service_logic"))
        pi_name = validate_name(body["pi_name"], "pi_name")
        slg_name = validate_name(body["pi_service_logic"], "pi_service_logic")
        d = threads.deferToThread(self.data.provision_platform_instance, pi_name, slg_name)
        d.addCallback(lambda _: f"platform instance '{pi_name}' provisioned with service logic '{slg_name}'")
        return d

    @defer.inlineCallbacks
    def r_provisioning(self, body):
        """Remove ``pi_name``; a connected robot is disconnected (service space torn down) first.

        With a master runtime both happen under the robot's lock (``robots.remove``), the lock its hello takes
        to check provisioning and open a session, so a hello racing this call either loses (refused) or wins
        and is then ended here: never a session left running for a removed robot."""
        require_fields(body, ("pi_name",))
        pi_name = validate_name(body["pi_name"], "pi_name")

        def remove():
            self.data.remove_platform_instance(pi_name)
        if self.robots is None:
            yield threads.deferToThread(remove)
            disconnected = False
        else:
            disconnected = yield self.robots.remove(pi_name, "its provisioning was removed", remove)
        return f"platform instance '{pi_name}' removed{' after disconnecting it' if disconnected else ''}"
