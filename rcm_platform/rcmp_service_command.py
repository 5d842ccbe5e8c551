"""Commands on service logics (read, provisioning, r_provisioning) and ``service_space/read``, behind the RDAPI.

Each command validates its input (``rcmp_command``), does its SQLite work in a thread (``deferToThread``) and
returns a Deferred firing with the ``reason`` of an OK answer or failing with a ``CommandError``. Reads of service
logics are answered from a ``ReadCache`` while the robotics data has not changed. Service spaces are live state
owned by the master runtime: ``spaces.describe(ss_name)`` (the ``MasterAgent``) answers for them, with this
module's renderers: ``describe`` (a space of the ``rcmp_ms.ServiceSpaceManager``) and ``describe_waiting`` (a space
waiting in line to be built).
"""

from twisted.internet import defer, threads

from .rcmp_command import command, NotFound, ReadCache, require_fields, validate_name, validate_service_logic


def describe_waiting(place, limit, public_ip):
    """The ``service_space/read`` payload of a space waiting to be built, ``place`` in line."""
    return {"r_nodes": [], "r_launchers": [], "public_ip": public_ip, "inbound_port": None,
            "ros_master_uri": None, "paired": False, "waiting": True,
            "reason": f"waiting to be built: number {place} in line; the platform builds at most "
                      f"{limit} service spaces at once (each server its own share)"}


def describe(host, ss_name):
    """The ``service_space/read`` payload (CONTRACTS §2, §8) of ``ss_name`` on ``host`` (a ServiceSpaceManager:
    ``spaces`` by name, ``public_ip``, optionally ``waiting_reason(ss_name)`` for a space waiting for room), or None
    when there is no such space. ``public_ip`` and ``server`` are those of the server hosting the space."""
    space = host.spaces.get(ss_name)
    if space is None:
        waiting = getattr(host, "waiting_reason", None)
        reason = waiting(ss_name) if waiting is not None else None
        if reason is None:
            return None
        return {"r_nodes": [], "r_launchers": [], "public_ip": None, "inbound_port": None, "ros_master_uri": None,
                "paired": False, "waiting": True, "server": None, "reason": reason}
    r_nodes, r_launchers = [], []
    for item in space.items:
        state, error = item.state, item.current_error
        if item.kind == "node":
            entry = {"sn_package": item.package, "sn_type": item.type_or_file, "sn_name": item.name,
                     "i_name": item.i_name, "state": state}
            if error:
                entry["error"] = error
            r_nodes.append(entry)
            continue
        entry = {"sl_package": item.package, "sl_file_launcher": item.type_or_file, "sl_name": item.name,
                 "associated_r_nodes": list(item.nodes), "i_name": item.i_name, "state": state}
        if error:
            entry["error"] = error
        r_launchers.append(entry)
        for node in item.nodes:
            package, node_type = item.node_types.get(node, (item.package, ""))
            r_nodes.append({"sn_package": package, "sn_type": node_type, "sn_name": node,
                            "i_name": item.i_name, "state": state, "launcher": item.name})
    payload = {"r_nodes": r_nodes, "r_launchers": r_launchers,
               "public_ip": getattr(space, "public_ip", None) or host.public_ip,
               "inbound_port": space.inbound_port, "ros_master_uri": space.ros_master_uri,
               "paired": space.paired}
    if getattr(space, "server", None) is not None:
        payload["server"] = space.server
    if not space.paired and not space.creating:
        payload["reason"] = space.why_unpaired()
    if space.driver_events:
        payload["rcm_driver_events"] = list(space.driver_events)
    return payload


class ServiceCommands:
    """``data``: RoboticsData; ``spaces``: object with ``describe(ss_name) -> dict | None`` (the MasterAgent) or
    None."""

    def __init__(self, data, spaces=None):
        self.data = data
        self.spaces = spaces
        self.cache = ReadCache(data)

    @command
    def read(self, slg_name=None):
        """All service logic names as ``[{"slg_name"}]``, or the items of one service logic."""
        if slg_name is None:
            return self._cached("names", lambda: [{"slg_name": n} for n in self.data.service_logic_names()])
        slg_name = validate_name(slg_name, "slg_name")

        def one():
            logic = self.data.service_logic(slg_name)
            if logic is None:
                raise NotFound(f"there is no service logic named '{slg_name}'")
            return logic
        return self._cached(("logic", slg_name), one)

    def _cached(self, key, compute):
        cached = self.cache.get(key)
        if cached is not None:
            return defer.succeed(cached)
        generation = self.data.generation
        d = threads.deferToThread(compute)
        d.addCallback(lambda value: self.cache.put(key, generation, value))
        return d

    @command
    def provisioning(self, body):
        """Store a new service logic with its service nodes and launchers (one transaction)."""
        slg_name, sn_list, sl_list, ss_side = validate_service_logic(body)
        d = threads.deferToThread(self.data.provision_service_logic, slg_name, sn_list, sl_list, ss_side)
        d.addCallback(lambda _: f"service logic '{slg_name}' provisioned with {len(sn_list)} service node(s) "
                                f"and {len(sl_list)} service launcher(s)")
        return d

    @command
    def r_provisioning(self, body):
        """Remove a service logic no provisioned robot uses."""
        require_fields(body, ("slg_name",))
        slg_name = validate_name(body["slg_name"], "slg_name")
        d = threads.deferToThread(self.data.remove_service_logic, slg_name)
        d.addCallback(lambda _: f"service logic '{slg_name}' removed")
        return d

    @command
    def service_space(self, ss_name):
        """The running service space of robot ``ss_name``; NotFound when it has none."""
        ss_name = validate_name(ss_name, "ss_name")
        described = self.spaces.describe(ss_name) if self.spaces is not None else None
        if described is None:
            return defer.fail(NotFound(f"there is no running service space named '{ss_name}'"))
        return defer.succeed(described)
