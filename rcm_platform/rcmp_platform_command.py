"""Commands on platform instances (robots) behind the RDAPI: read, provisioning and r_provisioning.

Each command validates its input (``rcmp_command``), does its SQLite work in a thread (``deferToThread``) and
returns a Deferred firing with the ``reason`` of an OK answer or failing with a ``CommandError``. Removing a
connected robot first asks the master runtime (``robots.remove``) to disconnect it and tear its service space
down; when the platform's VPN still holds a valid certificate for it, the answer and the log say how to revoke it
(``robots.certificate_advice``). Reads are answered from a ``ReadCache`` while the robotics data has not changed;
the robots' read, whose rows also carry the ``server`` of each robot's space, is the same object while neither the
data nor any robot's server changed (``placement``, counted from the ``ServiceSpaceManager``'s observers), so that
the RDAPI encodes it once (``Rdapi._encoded``) however often it is read.
"""

import logging

from twisted.internet import defer, threads

from .rcmp_command import BadRequest, Conflict, command, ReadCache, require_fields, validate_name

log = logging.getLogger("rcmp.platform")


class PlatformCommands:
    """``data``: RoboticsData; ``robots``: the master runtime (``remove(pi_name, reason, remove)``,
    ``certificate_advice(pi_name)``, and for the reads of CONTRACTS §8 ``server_rows()`` and ``server_of(pi_name)``;
    with ``spaces.observers`` its ``server_of`` answers are followed, else recomputed at every read) or None."""

    def __init__(self, data, robots=None):
        self.data = data
        self.robots = robots
        self.cache = ReadCache(data)
        self.placement = 0      # bumped whenever server_of() of a robot changed (or may have: a server came or went)
        self._placed = {}       # pi_name -> server_of(pi_name) as last seen, for the robots that have one
        self._answer = None     # (rows of the data, placement, those rows with their servers): the last read()
        observers = getattr(getattr(robots, "spaces", None), "observers", None)
        self._follows_placement = observers is not None and hasattr(robots, "server_of")
        if self._follows_placement:
            for name in list(getattr(robots.spaces, "spaces", {}) or {}):
                self._space_changed(name)
            observers.append(self._space_changed)

    def _space_changed(self, ss_name):
        """ServiceSpaceManager observer (on the reactor): count a change of a robot's server."""
        if ss_name is None:                 # a server joined or went
            self.placement += 1
            return
        server = self.robots.server_of(ss_name)
        if self._placed.get(ss_name) != server:
            if server is None:
                del self._placed[ss_name]
            else:
                self._placed[ss_name] = server
            self.placement += 1

    @command
    def read(self, pi_type=None):
        """The provisioned robots (master excluded), with (ext) the ``server`` hosting a robot's service space (when it
        has one); with
        ``pi_type`` S the servers instead: the master first, then the connected server VMs (CONTRACTS §8)."""
        if pi_type not in (None, "R", "S"):
            raise BadRequest(f"'pi_type' must be \"R\" (robots) or \"S\" (servers), not {pi_type[:40]!r}")
        if pi_type == "S":
            return defer.succeed(self.robots.server_rows() if self.robots is not None else [])
        cached = self.cache.get("platform_instances")
        if cached is not None:
            d = defer.succeed(cached)
        else:
            generation = self.data.generation
            d = threads.deferToThread(self.data.platform_instances)
            d.addCallback(lambda rows: self.cache.put("platform_instances", generation, rows))
        return d.addCallback(self._with_servers)

    def _with_servers(self, rows):
        """``rows`` (the data's, the same object while the data has not changed) with each robot's ``server``: the
        last answer again while neither ``rows`` nor ``placement`` changed."""
        server_of = getattr(self.robots, "server_of", None)
        if server_of is None:
            return rows
        last = self._answer
        if last is not None and last[0] is rows and last[1] == self.placement:
            return last[2]
        placement = self.placement
        answer = list(rows)
        for index, row in enumerate(answer):
            server = server_of(row["pi_name"])
            if server is not None:          # only robots with a service space have a server
                answer[index] = dict(row, server=server)
        if self._follows_placement:
            self._answer = (rows, placement, answer)
        return answer

    @command
    def provisioning(self, body):
        """Provision ``pi_name`` with the existing service logic ``pi_service_logic``."""
        require_fields(body, ("pi_name", "pi_service_logic"))
        pi_name = validate_name(body["pi_name"], "pi_name")
        slg_name = validate_name(body["pi_service_logic"], "pi_service_logic")
        if pi_name in getattr(self.robots, "servers", {}):
            raise Conflict(f"'{pi_name}' is the name of a connected server VM; give the robot another name")
        d = threads.deferToThread(self.data.provision_platform_instance, pi_name, slg_name)
        d.addCallback(lambda _: f"platform instance '{pi_name}' provisioned with service logic '{slg_name}'")
        return d

    @defer.inlineCallbacks
    def r_provisioning(self, body):
        """Remove ``pi_name``; a connected robot is disconnected (service space torn down) first.

        With a master runtime both happen under the robot's lock (``robots.remove``), the lock its hello takes
        to check provisioning and open a session, so a hello racing this call either loses (refused) or wins
        and is then ended here: never a session left running for a removed robot. The robot's VPN certificate is not
        revoked (removing and provisioning again is how a robot changes its service logic); when it is still valid,
        the answer and the log say how to revoke it."""
        require_fields(body, ("pi_name",))
        pi_name = validate_name(body["pi_name"], "pi_name")

        def remove():
            self.data.remove_platform_instance(pi_name)
        if self.robots is None:
            yield threads.deferToThread(remove)
            disconnected = False
        else:
            disconnected = yield self.robots.remove(pi_name, "its provisioning was removed", remove)
        answer = f"platform instance '{pi_name}' removed{' after disconnecting it' if disconnected else ''}"
        advice = getattr(self.robots, "certificate_advice", lambda name: None)(pi_name)
        if advice:
            answer = f"{answer}; {advice}"
            log.warning("%s", answer)
        return answer
