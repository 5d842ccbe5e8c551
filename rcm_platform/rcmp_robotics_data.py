"""The robotics data of the master: one SQLite file (``HOME/robotics_data.db``), its schema and every read and write.

Owns the schema and its version (table ``schema_version``), the default service logics written on first start,
the provisioning (platform instances with the master's own row, service logics with their service nodes and
service launchers) and the live state (connections, service spaces), which is forgotten at every start because
it describes processes of a previous life of the agent.

Access is synchronous and thread-safe: one connection guarded by one lock; every write is one transaction
(``BEGIN IMMEDIATE`` ... ``COMMIT``, rolled back on any error), so a crash or a rejected request never leaves half
a service logic behind. ``write_batch`` runs several writes in one transaction, each in its own savepoint (the
master's live-state writes, which come by the thousand while a fleet pairs: one commit for all that waited, and
a write that fails leaves the others). Callers on the reactor thread wrap calls with ``deferToThread``.
``generation`` counts committed transactions; readers that cache answers (``rcmp_command.ReadCache``) compare it
to know their copy is current.
Names are validated by ``rcmp_command`` before they get here.

Also holds the RDAPI's bearer tokens (table ``rdapi_token``: name, role, SHA-256 of the token, never the token
itself), written by ``rcmp_n token ...`` through its own connection while the agent may be running; the agent
re-reads them (``tokens()``) to see such changes. Schema version 2 added that table; a version 1 file is
migrated in place when opened.
"""

import datetime
import sqlite3
import threading

from .rcmp_command import TOKEN_ROLES, Conflict, NotFound

SCHEMA_VERSION = 2

TOKEN_TABLE = """
CREATE TABLE rdapi_token (
    name TEXT PRIMARY KEY,
    role TEXT NOT NULL CHECK (role IN ('read', 'admin')),
    sha256 TEXT NOT NULL UNIQUE,
    created TEXT NOT NULL
);
"""

SCHEMA = """
CREATE TABLE schema_version (
    version INTEGER NOT NULL
);
CREATE TABLE service_logic (
    slg_name TEXT PRIMARY KEY,
    ss_side TEXT NOT NULL DEFAULT 'S' CHECK (ss_side IN ('S', 'R')),
    is_default INTEGER NOT NULL DEFAULT 0,
    created TEXT NOT NULL
);
CREATE TABLE service_node (
    slg_name TEXT NOT NULL REFERENCES service_logic (slg_name) ON DELETE CASCADE,
    position INTEGER NOT NULL,
    sn_package TEXT NOT NULL,
    sn_type TEXT NOT NULL,
    sn_name TEXT NOT NULL,
    sn_params TEXT NOT NULL DEFAULT '',
    sn_side TEXT NOT NULL CHECK (sn_side IN ('S', 'R')),
    PRIMARY KEY (slg_name, position)
);
CREATE TABLE service_launcher (
    slg_name TEXT NOT NULL REFERENCES service_logic (slg_name) ON DELETE CASCADE,
    position INTEGER NOT NULL,
    sl_package TEXT NOT NULL,
    sl_file_launcher TEXT NOT NULL,
    sl_name TEXT NOT NULL,
    sl_params TEXT NOT NULL DEFAULT '',
    sl_side TEXT NOT NULL CHECK (sl_side IN ('S', 'R')),
    PRIMARY KEY (slg_name, position)
);
CREATE TABLE platform_instance (
    pi_name TEXT PRIMARY KEY,
    slg_name TEXT REFERENCES service_logic (slg_name),
    is_master INTEGER NOT NULL DEFAULT 0,
    address TEXT,
    inbound_open_ports TEXT NOT NULL DEFAULT '',
    created TEXT NOT NULL
);
CREATE TABLE connection (
    pi_name TEXT PRIMARY KEY REFERENCES platform_instance (pi_name) ON DELETE CASCADE,
    address TEXT NOT NULL,
    paired INTEGER NOT NULL DEFAULT 0,
    since TEXT NOT NULL
);
CREATE TABLE service_space (
    ss_name TEXT PRIMARY KEY REFERENCES platform_instance (pi_name) ON DELETE CASCADE,
    ros_master_uri TEXT,
    inbound_port INTEGER,
    created TEXT NOT NULL
);
""" + TOKEN_TABLE

# version -> the statements that bring a file of that version to the next one
MIGRATIONS = {1: TOKEN_TABLE}

# Written on first start only: a user may remove them and they stay removed.
DEFAULT_SERVICE_LOGICS = [
    ("empty", [], []),
    ("fiware_base", [
        {"sn_package": "rcm", "sn_type": "rcm_driver.py", "sn_name": "rcm_driver", "sn_params": "",
         "sn_side": "S"},
        {"sn_package": "firos", "sn_type": "core.py", "sn_name": "firos", "sn_params": "", "sn_side": "S"},
    ], []),
]

NODE_COLUMNS = ("sn_package", "sn_type", "sn_name", "sn_params", "sn_side")
LAUNCHER_COLUMNS = ("sl_package", "sl_file_launcher", "sl_name", "sl_params", "sl_side")


class DataError(Exception):
    """The database file cannot be used (not a database, newer schema, unreadable)."""


def _now():
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


class RoboticsData:
    """The master's SQLite database. Every method may be called from any thread."""

    def __init__(self, path, forget_live_state=True):
        self.path = path
        self._forget_live_state = forget_live_state
        self.generation = 0
        self.observers = []   # fn(generation) after every committed write, on the writing thread (the console)
        self._lock = threading.Lock()
        self._batch_thread = None   # the thread running write_batch: its writes join the batch's transaction
        try:
            self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=30.0)
            self._db.execute("PRAGMA foreign_keys = ON")
            with self._lock:
                self._open()
        except sqlite3.DatabaseError as exc:
            raise DataError(f"{path}: cannot use the robotics data: {exc}") from None

    # -- plumbing -------------------------------------------------------------------------------------------

    def _open(self):
        tables = {row[0] for row in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        self._begin()
        try:
            if "schema_version" not in tables:
                if tables:
                    raise DataError(f"{self.path}: not a robotics data file (it has tables but no schema_version)")
                for statement in SCHEMA.split(";"):
                    if statement.strip():
                        self._db.execute(statement)
                self._db.execute("INSERT INTO schema_version (version) VALUES (?)", (SCHEMA_VERSION,))
                for name, nodes, launchers in DEFAULT_SERVICE_LOGICS:
                    self._insert_service_logic(name, nodes, launchers, "S", is_default=True)
            else:
                row = self._db.execute("SELECT max(version) FROM schema_version").fetchone()
                version = row[0] if row else None
                while version in MIGRATIONS:
                    for statement in MIGRATIONS[version].split(";"):
                        if statement.strip():
                            self._db.execute(statement)
                    version += 1
                    self._db.execute("DELETE FROM schema_version")
                    self._db.execute("INSERT INTO schema_version (version) VALUES (?)", (version,))
                if version != SCHEMA_VERSION:
                    raise DataError(f"{self.path}: schema version {version} is not the supported version "
                                    f"{SCHEMA_VERSION}")
            if self._forget_live_state:  # live state of a previous life of the agent
                self._db.execute("DELETE FROM service_space")
                self._db.execute("DELETE FROM connection")
            self._db.execute("COMMIT")
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self.generation += 1

    def _begin(self):
        self._db.execute("BEGIN IMMEDIATE")

    def _write(self, func, *args):
        """Run ``func(*args)`` in one transaction under the lock; bump ``generation`` when it committed. Inside
        ``write_batch`` (on its thread) ``func`` runs in the batch's transaction instead (its savepoint)."""
        if self._batch_thread == threading.get_ident():
            return func(*args)
        with self._lock:
            self._begin()
            try:
                result = func(*args)
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self.generation += 1
            generation = self.generation
        self._tell_observers(generation)
        return result

    def write_batch(self, calls):
        """Run ``calls``, ``[(fn, args)]`` (write methods of this object, such as ``set_paired``), in order, in one
        transaction, each in its own savepoint: one that raises is rolled back alone (nothing of it is left) and
        the others are kept. One commit, ``generation`` bumped once and the observers told once for the whole
        batch. Returns ``[(True, result) or (False, exception)]`` in the order of ``calls``. If the commit itself
        fails, nothing of the batch is kept and the exception is raised."""
        results = []
        with self._lock:
            self._begin()
            self._batch_thread = threading.get_ident()
            try:
                for fn, args in calls:
                    self._db.execute("SAVEPOINT batch_write")
                    try:
                        result = fn(*args)
                    except Exception as exc:
                        self._db.execute("ROLLBACK TO batch_write")
                        self._db.execute("RELEASE batch_write")
                        results.append((False, exc))
                    else:
                        self._db.execute("RELEASE batch_write")
                        results.append((True, result))
                self._db.execute("COMMIT")
            except BaseException:
                if self._db.in_transaction:     # SQLite may have rolled back already (a full disk, say)
                    self._db.execute("ROLLBACK")
                raise
            finally:
                self._batch_thread = None
            self.generation += 1
            generation = self.generation
        self._tell_observers(generation)
        return results

    def _tell_observers(self, generation):
        for observer in list(self.observers):
            observer(generation)

    def _read(self, func, *args):
        with self._lock:
            return func(*args)

    def close(self):
        with self._lock:
            self._db.close()

    # -- the master ------------------------------------------------------------------------------------------

    def set_master(self, name, address, inbound_open_ports):
        """Record the master's own row (replacing the row of a previous master name); Conflict if a robot has it."""
        ports = ", ".join(str(p) for p in inbound_open_ports)

        def write():
            row = self._db.execute("SELECT is_master FROM platform_instance WHERE pi_name = ?", (name,)).fetchone()
            if row is not None and not row[0]:
                raise Conflict(f"the master's name '{name}' is already the name of a provisioned robot")
            self._db.execute("DELETE FROM platform_instance WHERE is_master = 1 AND pi_name != ?", (name,))
            self._db.execute(
                "INSERT INTO platform_instance (pi_name, slg_name, is_master, address, inbound_open_ports, created) "
                "VALUES (?, NULL, 1, ?, ?, ?) ON CONFLICT (pi_name) DO UPDATE SET address = excluded.address, "
                "inbound_open_ports = excluded.inbound_open_ports", (name, address, ports, _now()))
        self._write(write)

    def master(self):
        """The master's row: ``{"pi_name", "address", "inbound_open_ports": [int]}`` or None before set_master."""
        def read():
            row = self._db.execute("SELECT pi_name, address, inbound_open_ports FROM platform_instance "
                                   "WHERE is_master = 1").fetchone()
            if row is None:
                return None
            ports = [int(p) for p in row[2].split(",") if p.strip()]
            return {"pi_name": row[0], "address": row[1], "inbound_open_ports": ports}
        return self._read(read)

    # -- platform instances ----------------------------------------------------------------------------------

    def platform_instances(self):
        """The RDAPI rows ``{"pi_name", "service_logic", "connected", "paired"}``, master excluded, in provisioning order."""
        def read():
            rows = self._db.execute(
                "SELECT p.pi_name, p.slg_name, c.pi_name IS NOT NULL, coalesce(c.paired, 0) "
                "FROM platform_instance p LEFT JOIN connection c ON c.pi_name = p.pi_name "
                "WHERE p.is_master = 0 ORDER BY p.rowid").fetchall()
            return [{"pi_name": r[0], "service_logic": r[1], "connected": bool(r[2]), "paired": bool(r[3])}
                    for r in rows]
        return self._read(read)

    def platform_instance(self, pi_name):
        """One robot's row plus ``"address"`` (where it connected from, or last connected from), or None."""
        def read():
            r = self._db.execute(
                "SELECT p.pi_name, p.slg_name, c.pi_name IS NOT NULL, coalesce(c.paired, 0), "
                "coalesce(c.address, p.address) FROM platform_instance p "
                "LEFT JOIN connection c ON c.pi_name = p.pi_name WHERE p.is_master = 0 AND p.pi_name = ?",
                (pi_name,)).fetchone()
            if r is None:
                return None
            return {"pi_name": r[0], "service_logic": r[1], "connected": bool(r[2]), "paired": bool(r[3]),
                    "address": r[4]}
        return self._read(read)

    def addresses(self):
        """``{pi_name: address}`` of every robot (master excluded), as ``platform_instance`` gives it, in one query."""
        def read():
            return dict(self._db.execute(
                "SELECT p.pi_name, coalesce(c.address, p.address) FROM platform_instance p "
                "LEFT JOIN connection c ON c.pi_name = p.pi_name WHERE p.is_master = 0").fetchall())
        return self._read(read)

    def provision_platform_instance(self, pi_name, slg_name):
        """Provision robot ``pi_name`` running ``slg_name``; NotFound (no such service logic) / Conflict (name taken)."""
        def write():
            if self._db.execute("SELECT 1 FROM service_logic WHERE slg_name = ?", (slg_name,)).fetchone() is None:
                raise NotFound(f"there is no service logic named '{slg_name}'")
            row = self._db.execute("SELECT is_master FROM platform_instance WHERE pi_name = ?", (pi_name,)).fetchone()
            if row is not None:
                if row[0]:
                    raise Conflict(f"'{pi_name}' is the name of the master")
                raise Conflict(f"a platform instance named '{pi_name}' is already provisioned")
            self._db.execute("INSERT INTO platform_instance (pi_name, slg_name, is_master, created) "
                             "VALUES (?, ?, 0, ?)", (pi_name, slg_name, _now()))
        self._write(write)

    def remove_platform_instance(self, pi_name):
        """Remove robot ``pi_name`` and its live state; NotFound if it is not provisioned."""
        def write():
            cur = self._db.execute("DELETE FROM platform_instance WHERE pi_name = ? AND is_master = 0", (pi_name,))
            if cur.rowcount == 0:
                raise NotFound(f"there is no platform instance named '{pi_name}'")
        self._write(write)

    # -- service logics --------------------------------------------------------------------------------------

    def service_logic_names(self):
        """Names of every service logic, defaults first, then in provisioning order."""
        def read():
            return [r[0] for r in self._db.execute("SELECT slg_name FROM service_logic ORDER BY rowid")]
        return self._read(read)

    def service_logic(self, slg_name):
        """``{"ss_side", "sn_list", "sl_list"}`` of ``slg_name`` (items in the order given), or None."""
        def read():
            row = self._db.execute("SELECT ss_side FROM service_logic WHERE slg_name = ?", (slg_name,)).fetchone()
            if row is None:
                return None
            nodes = self._db.execute(f"SELECT {', '.join(NODE_COLUMNS)} FROM service_node WHERE slg_name = ? "
                                     "ORDER BY position", (slg_name,)).fetchall()
            launchers = self._db.execute(f"SELECT {', '.join(LAUNCHER_COLUMNS)} FROM service_launcher "
                                         "WHERE slg_name = ? ORDER BY position", (slg_name,)).fetchall()
            return {"ss_side": row[0],
                    "sn_list": [dict(zip(NODE_COLUMNS, r)) for r in nodes],
                    "sl_list": [dict(zip(LAUNCHER_COLUMNS, r)) for r in launchers]}
        return self._read(read)

    def _insert_service_logic(self, slg_name, sn_list, sl_list, ss_side, is_default=False):
        self._db.execute("INSERT INTO service_logic (slg_name, ss_side, is_default, created) VALUES (?, ?, ?, ?)",
                         (slg_name, ss_side, int(is_default), _now()))
        self._db.executemany(
            f"INSERT INTO service_node (slg_name, position, {', '.join(NODE_COLUMNS)}) VALUES (?, ?, ?, ?, ?, ?, ?)",
            [(slg_name, i) + tuple(n.get(c, "") for c in NODE_COLUMNS) for i, n in enumerate(sn_list)])
        self._db.executemany(
            f"INSERT INTO service_launcher (slg_name, position, {', '.join(LAUNCHER_COLUMNS)}) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            [(slg_name, i) + tuple(l.get(c, "") for c in LAUNCHER_COLUMNS) for i, l in enumerate(sl_list)])

    def provision_service_logic(self, slg_name, sn_list, sl_list, ss_side="S"):
        """Store a service logic with its items in one transaction; Conflict if the name is taken."""
        def write():
            if self._db.execute("SELECT 1 FROM service_logic WHERE slg_name = ?", (slg_name,)).fetchone():
                raise Conflict(f"a service logic named '{slg_name}' already exists")
            self._insert_service_logic(slg_name, sn_list, sl_list, ss_side)
        self._write(write)

    def remove_service_logic(self, slg_name):
        """Remove a service logic and its items; NotFound, or Conflict while a provisioned robot uses it."""
        def write():
            if self._db.execute("SELECT 1 FROM service_logic WHERE slg_name = ?", (slg_name,)).fetchone() is None:
                raise NotFound(f"there is no service logic named '{slg_name}'")
            users = [r[0] for r in self._db.execute(
                "SELECT pi_name FROM platform_instance WHERE slg_name = ? ORDER BY rowid LIMIT 4", (slg_name,))]
            if users:
                shown = ", ".join(f"'{u}'" for u in users[:3]) + (" and others" if len(users) > 3 else "")
                raise Conflict(f"service logic '{slg_name}' is used by the platform instance(s) {shown}")
            self._db.execute("DELETE FROM service_logic WHERE slg_name = ?", (slg_name,))
        self._write(write)

    # -- live state ------------------------------------------------------------------------------------------

    def set_connected(self, pi_name, address):
        """Robot ``pi_name`` connected from ``address`` (not paired yet); NotFound if it is not provisioned."""
        def write():
            cur = self._db.execute("UPDATE platform_instance SET address = ? WHERE pi_name = ? AND is_master = 0",
                                   (address, pi_name))
            if cur.rowcount == 0:
                raise NotFound(f"there is no platform instance named '{pi_name}'")
            self._db.execute("INSERT INTO connection (pi_name, address, paired, since) VALUES (?, ?, 0, ?) "
                             "ON CONFLICT (pi_name) DO UPDATE SET address = excluded.address, paired = 0, "
                             "since = excluded.since", (pi_name, address, _now()))
        self._write(write)

    def set_paired(self, pi_name, paired):
        """Mark a connected robot paired or not; returns False (and changes nothing) if it is not connected."""
        def write():
            cur = self._db.execute("UPDATE connection SET paired = ? WHERE pi_name = ?", (int(bool(paired)), pi_name))
            return cur.rowcount > 0
        return self._write(write)

    def set_service_space(self, pi_name, ros_master_uri, inbound_port):
        """Record the running service space of ``pi_name``; NotFound if it is not provisioned."""
        def write():
            if self._db.execute("SELECT 1 FROM platform_instance WHERE pi_name = ?", (pi_name,)).fetchone() is None:
                raise NotFound(f"there is no platform instance named '{pi_name}'")
            self._db.execute("INSERT INTO service_space (ss_name, ros_master_uri, inbound_port, created) "
                             "VALUES (?, ?, ?, ?) ON CONFLICT (ss_name) DO UPDATE SET "
                             "ros_master_uri = excluded.ros_master_uri, inbound_port = excluded.inbound_port",
                             (pi_name, ros_master_uri, inbound_port, _now()))
        self._write(write)

    def service_space(self, ss_name):
        """``{"ss_name", "ros_master_uri", "inbound_port"}`` of a running service space, or None."""
        def read():
            r = self._db.execute("SELECT ss_name, ros_master_uri, inbound_port FROM service_space WHERE ss_name = ?",
                                 (ss_name,)).fetchone()
            return None if r is None else {"ss_name": r[0], "ros_master_uri": r[1], "inbound_port": r[2]}
        return self._read(read)

    def set_disconnected(self, pi_name):
        """Robot ``pi_name`` is gone: not connected, not paired, no service space. No error if it was not."""
        def write():
            self._db.execute("DELETE FROM service_space WHERE ss_name = ?", (pi_name,))
            self._db.execute("DELETE FROM connection WHERE pi_name = ?", (pi_name,))
        self._write(write)

    def integrity_check(self):
        """SQLite's own check of the file: ``"ok"`` when it is sound."""
        return self._read(lambda: self._db.execute("PRAGMA integrity_check").fetchone()[0])

    # -- RDAPI tokens ------------------------------------------------------------------------------------------

    def add_token(self, name, role, sha256):
        """Keep a new token's hash under ``name`` with ``role`` (read | admin); Conflict if the name is taken."""
        if role not in TOKEN_ROLES:
            raise ValueError(f"unknown token role {role!r}")

        def write():
            if self._db.execute("SELECT 1 FROM rdapi_token WHERE name = ?", (name,)).fetchone():
                raise Conflict(f"a token named '{name}' already exists (revoke it first to replace it)")
            self._db.execute("INSERT INTO rdapi_token (name, role, sha256, created) VALUES (?, ?, ?, ?)",
                             (name, role, sha256, _now()))
        self._write(write)

    def revoke_token(self, name):
        """Forget the token ``name``; NotFound if there is none."""
        def write():
            if self._db.execute("DELETE FROM rdapi_token WHERE name = ?", (name,)).rowcount == 0:
                raise NotFound(f"there is no token named '{name}'")
        self._write(write)

    def tokens(self):
        """Every token as ``{"name", "role", "sha256", "created"}``, oldest first."""
        def read():
            rows = self._db.execute("SELECT name, role, sha256, created FROM rdapi_token ORDER BY rowid").fetchall()
            return [dict(zip(("name", "role", "sha256", "created"), r)) for r in rows]
        return self._read(read)
