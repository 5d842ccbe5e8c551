"""The whitelist: which robots and which of their topics FIROS maps (CONTRACTS §3, seed "Firos whitelist").

Format: {"<robot regex>": {"publisher": [topic regexes], "subscriber": [topic regexes]}}, from the broker's
point of view: publisher = broker → ROS, subscriber = ROS → broker. Robot names and topic names (relative to
the robot's namespace, e.g. "move_base/goal") must match a regex entirely (re.fullmatch). A subscriber entry may
also be an object naming limits for the topics it matches: {"topic": "<regex>", "max_rate": <per second>,
"max_size": <bytes>} (both optional; where several entries match, the smallest of each counts). A publisher entry
may be an object declaring the message type of a topic it names plainly, {"topic": "p1", "type": "std_msgs/String"}:
the one way a topic absent from the ROS graph can be commanded (`declared_type`; docs/DECISIONS.md, "FIROS commands
only topics in the graph"). An entry whose pattern is the topic's own name, with no regex characters, "names it
plainly" (`names_plainly`): the rule for images and point clouds (`discovery.LARGE_MESSAGE_TYPES`) and for declared
types. Owns validation, matching, limits, declared types and the in-memory edits of the HTTP API (write merges, an
entry replacing the one with the same pattern; remove deletes the entries with the given patterns; restore reloads
the file).

Python's `re` backtracks, and there is no `re2` in Debian to swap in, so a pattern is accepted only in shapes
whose matching cost stays small (docs/SECURITY.md, "FIROS"): at most MAX_PATTERN characters, no backreferences,
no repetition inside a repetition, no alternation inside a repetition (`(a|a)*b` costs 2^n), and repetitions
whose widths multiplied stay within what two open-ended ones give (`.*foo.*` yes, `.*a.*b.*c` no: each
open-ended repetition multiplies the worst cost by the name's length), checked on the parsed pattern. Names
longer than MAX_NAME are never matched, so the worst accepted pattern costs milliseconds.
"""

import copy
import os
import re
import threading

try:                                        # Python 3.11+: the parser of re, with its opcodes
    import re._constants as sre
    import re._parser as sre_parse
except ImportError:                         # older Pythons name them sre_constants / sre_parse
    import sre_constants as sre
    import sre_parse

from include.config import ConfigError, read_json
from include.ngsi_encoding import NgsiEncodingError, attribute_type_to_message_type

KINDS = ("publisher", "subscriber")
LIMIT_KEYS = ("max_rate", "max_size")
MAX_PATTERN = 256
MAX_NAME = 256       # robot and topic names longer than this match nothing
MAX_COST = (MAX_NAME + 1) ** 2   # the product of the repetitions' widths: two open-ended ones at most
_PLAIN_TOPIC = re.compile(r"[A-Za-z0-9_/]+")
# possessive repetitions and atomic groups are Python 3.11's; an older parser never produces them
_ATOMIC_GROUP = getattr(sre, "ATOMIC_GROUP", None)
_REPEATS = tuple(op for op in (sre.MAX_REPEAT, sre.MIN_REPEAT, getattr(sre, "POSSESSIVE_REPEAT", None))
                 if op is not None)


class WhitelistError(ValueError):
    """A whitelist document is malformed (bad shape or a regex that does not compile)."""


def validate(data):
    """Return {robot_regex: {"publisher": [..], "subscriber": [..]}} or raise WhitelistError."""
    if not isinstance(data, dict):
        raise WhitelistError("the whitelist must be a JSON object {\"robot regex\": {\"publisher\": [...], "
                             "\"subscriber\": [...]}}")
    clean = {}
    for robot, entry in data.items():
        _compile(robot, f"robot regex {robot!r}")
        if entry is None:
            entry = {}
        if not isinstance(entry, dict):
            raise WhitelistError(f"\"{robot}\" must map to an object with \"publisher\" and \"subscriber\" lists")
        unknown = set(entry) - set(KINDS)
        if unknown:
            raise WhitelistError(f"\"{robot}\" has unknown keys {sorted(unknown)}; only publisher and subscriber")
        clean[robot] = {}
        for kind in KINDS:
            topics = entry.get(kind, [])
            if not isinstance(topics, list):
                raise WhitelistError(f"\"{robot}\".{kind} must be a list of topic regexes (strings)")
            clean[robot][kind] = [_entry(topic, robot, kind) for topic in topics]
    return clean


def _entry(topic, robot, kind):
    """A validated topic entry: a regex (str), or for subscriber topics {"topic", "max_rate", "max_size"}, or for
    publisher topics {"topic": a plain name, "type": "pkg/Type"} (the type written "pkg/Type" however given)."""
    where = f"\"{robot}\".{kind}"
    if isinstance(topic, dict) and kind == "publisher":
        return _typed_entry(topic, where)
    if isinstance(topic, dict) and kind == "subscriber":
        unknown = set(topic) - {"topic"} - set(LIMIT_KEYS)
        if unknown or not isinstance(topic.get("topic"), str):
            raise WhitelistError(f"an entry of {where} given as an object needs \"topic\" (a regex) and may have "
                                 f"\"max_rate\" and \"max_size\", nothing else")
        rate, size = topic.get("max_rate"), topic.get("max_size")
        if rate is not None and (isinstance(rate, bool) or not isinstance(rate, (int, float)) or not rate > 0):
            raise WhitelistError(f"max_rate of {topic['topic']!r} in {where} must be a number of messages per "
                                 f"second above zero, not {rate!r}")
        if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
            raise WhitelistError(f"max_size of {topic['topic']!r} in {where} must be a whole number of bytes, "
                                 f"not {size!r}")
        _compile(topic["topic"], f"topic regex {topic['topic']!r} of {where}")
        return dict(topic)
    if not isinstance(topic, str):
        raise WhitelistError(f"{where} must be a list of topic regexes (strings) or objects")
    _compile(topic, f"topic regex {topic!r} of {where}")
    return topic


def _typed_entry(entry, where):
    """A publisher entry given as an object: {"topic": a plain topic name, "type": its message type}."""
    name, declared = entry.get("topic"), entry.get("type")
    if set(entry) != {"topic", "type"} or not isinstance(name, str) or not isinstance(declared, str):
        raise WhitelistError(f"an entry of {where} given as an object needs \"topic\" (a topic name) and "
                             f"\"type\" (its message type, like \"std_msgs/String\"), nothing else")
    if len(name) > MAX_NAME or not _PLAIN_TOPIC.fullmatch(name):
        raise WhitelistError(f"\"topic\" {name[:80]!r} of {where} must be the topic's own name (letters, digits, "
                             f"_ and /), not a regular expression, when it declares a type")
    try:
        return {"topic": name, "type": attribute_type_to_message_type(declared)}
    except NgsiEncodingError:
        raise WhitelistError(f"\"type\" {declared[:80]!r} of {name!r} in {where} is not a message type like "
                             f"\"std_msgs/String\"") from None


def pattern_of(entry):
    """The topic regex of a whitelist entry (a str, or an object's "topic")."""
    return entry["topic"] if isinstance(entry, dict) else entry


def _compile(pattern, what):
    if len(pattern) > MAX_PATTERN:
        raise WhitelistError(f"{what[:80]}... is longer than {MAX_PATTERN} characters")
    try:
        compiled = re.compile(pattern)
        tree = sre_parse.parse(pattern)
    except (re.error, RecursionError, OverflowError) as exc:
        raise WhitelistError(f"{what} is not a valid regular expression: {exc}") from None
    problem = costly_shape(tree)
    if problem:
        raise WhitelistError(f"{what} is refused: {problem}; its matching time could explode")
    return compiled


def costly_shape(tree):
    """Why a parsed pattern could backtrack badly (a sentence), or None when its shape is safe."""
    cost = 1

    def walk(items, repeated):
        nonlocal cost
        for op, av in items:
            if op in _REPEATS:
                low, high, sub = av
                if high > 1:
                    if repeated:
                        return "a repetition inside a repetition"
                    cost *= min(high, MAX_NAME) + 1
                    if cost > MAX_COST:
                        return "too many repetitions (at most two open-ended ones like .*)"
                problem = walk(sub, repeated or high > 1)
            elif op == sre.BRANCH:
                if repeated:
                    return "an alternation inside a repetition (use a character class like [ab])"
                problem = next((p for p in (walk(branch, repeated) for branch in av[1]) if p), None)
            elif op == sre.SUBPATTERN:
                problem = walk(av[-1], repeated)
            elif op in (sre.ASSERT, sre.ASSERT_NOT):
                problem = walk(av[1], repeated)
            elif op == _ATOMIC_GROUP:
                problem = walk(av, repeated)
            elif op in (sre.GROUPREF, sre.GROUPREF_EXISTS):
                return "a backreference"
            else:
                problem = None
            if problem:
                return problem
        return None

    return walk(tree.data, False)


class Whitelist:
    """The whitelist in memory, safe to use from several threads."""

    def __init__(self, path, data=None):
        self.path = path
        self._lock = threading.Lock()
        self._data = {}
        self._compiled = []
        if data is None:
            self.restore()
        else:
            self._set(validate(data))

    @classmethod
    def load(cls, config_dir):
        """The whitelist of CONFIG_DIR/whitelist.json; ConfigError (one line) if it is wrong."""
        path = os.path.join(config_dir, "whitelist.json")
        return cls(path)

    def restore(self):
        """Reload whitelist.json (ConfigError if it is now wrong; the whitelist in memory is then unchanged)."""
        data = read_json(self.path, "whitelist")
        try:
            clean = validate(data)
        except WhitelistError as exc:
            raise ConfigError(self.path, str(exc)) from None
        with self._lock:
            self._set(clean)

    def _set(self, clean):
        self._data = clean
        self._compiled = [(re.compile(robot), {k: [(re.compile(pattern_of(t)), t) for t in entry.get(k, [])]
                                               for k in KINDS})
                          for robot, entry in clean.items()]

    def snapshot(self):
        with self._lock:
            return copy.deepcopy(self._data)

    def write(self, data):
        """Merge ``data`` (same format) into the whitelist in memory; WhitelistError changes nothing."""
        clean = validate(data)
        with self._lock:
            merged = copy.deepcopy(self._data)
            for robot, entry in clean.items():
                target = merged.setdefault(robot, {k: [] for k in KINDS})
                for kind in KINDS:
                    listed = target.setdefault(kind, [])
                    for topic in entry.get(kind, []):
                        same = [i for i, t in enumerate(listed) if pattern_of(t) == pattern_of(topic)]
                        if same:
                            listed[same[0]] = topic
                        else:
                            listed.append(topic)
            self._set(merged)

    def remove(self, data):
        """Remove the listed topic regexes; a robot given with no lists (or left with none) is removed."""
        clean = validate(data)
        with self._lock:
            merged = copy.deepcopy(self._data)
            for robot, entry in clean.items():
                if robot not in merged:
                    continue
                if not any(entry.get(k) for k in KINDS):
                    del merged[robot]
                    continue
                for kind in KINDS:
                    gone = {pattern_of(t) for t in entry.get(kind, [])}
                    merged[robot][kind] = [t for t in merged[robot].get(kind, []) if pattern_of(t) not in gone]
                if not any(merged[robot].get(k) for k in KINDS):
                    del merged[robot]
            self._set(merged)

    def declared_types(self, robot):
        """{topic: "pkg/Type"} of the publisher topics whose type entries matching ``robot`` declare; a topic
        declared with two different types is left out (which one is meant cannot be told)."""
        found = {}
        if len(robot) > MAX_NAME:
            return found
        with self._lock:
            compiled = self._compiled
        for rx, topics in compiled:
            if rx.fullmatch(robot):
                for _, entry in topics["publisher"]:
                    if isinstance(entry, dict):
                        found.setdefault(entry["topic"], set()).add(entry["type"])
        return {topic: types.pop() for topic, types in found.items() if len(types) == 1}

    def declared_type(self, robot, topic):
        """The message type ("pkg/Type") a publisher entry matching ``robot`` declares for ``topic``, or None."""
        return self.declared_types(robot).get(topic)

    def robot_allowed(self, robot):
        if len(robot) > MAX_NAME:
            return False
        with self._lock:
            return any(rx.fullmatch(robot) for rx, _ in self._compiled)

    def topic_kinds(self, robot, topic):
        """The set of kinds ("publisher", "subscriber") under which ``topic`` (relative name) is listed."""
        kinds = set()
        for kind, _ in self._matching(robot, topic):
            kinds.add(kind)
        return kinds

    def names_plainly(self, robot, topic):
        """The set of kinds under which an entry names ``topic`` plainly: its pattern is the topic's own name
        with no regex characters (``camera/image_raw``, not ``camera/.*``)."""
        if not _PLAIN_TOPIC.fullmatch(topic):
            return set()
        return {kind for kind, entry in self._matching(robot, topic) if pattern_of(entry) == topic}

    def topic_limits(self, robot, topic):
        """(max_rate or None, max_size or None) of a subscriber topic: the smallest that matching entries set."""
        limits = {key: None for key in LIMIT_KEYS}
        for kind, entry in self._matching(robot, topic):
            if kind == "subscriber" and isinstance(entry, dict):
                for key in LIMIT_KEYS:
                    if entry.get(key) is not None:
                        limits[key] = entry[key] if limits[key] is None else min(limits[key], entry[key])
        return limits["max_rate"], limits["max_size"]

    def _matching(self, robot, topic):
        """[(kind, entry)] of the entries whose robot regex matches ``robot`` and topic regex ``topic``."""
        if len(robot) > MAX_NAME or len(topic) > MAX_NAME:
            return []
        with self._lock:
            compiled = self._compiled
        return [(kind, entry) for rx, topics in compiled if rx.fullmatch(robot)
                for kind in KINDS for topic_rx, entry in topics[kind] if topic_rx.fullmatch(topic)]
