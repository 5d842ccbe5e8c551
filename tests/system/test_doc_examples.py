"""The user documentation's shell examples run as they are written, against a demo platform: a page that drifts
from what the platform does fails here.

Which pages: ``DOCUMENTS``. Which examples: the fenced blocks right after a marker line, an HTML comment that
GitHub does not show:

- ``<!-- runnable -->``: the block runs. A block whose lines start with ``$ `` is a terminal session: each
  ``$ `` line (with the lines it continues with a trailing ``\\``, and the lines of a here-document it opens,
  ``<<EOF`` up to the line ``EOF``) is a command typed into one bash, so shell variables carry from one command to
  the next (``TOKEN=$(...)``), and the lines up to the next command are the output the page shows for it. A block
  without ``$ `` lines is a script, run in that bash with ``set -e``.
- ``<!-- runnable: eventually -->``: the same, for commands that read something that arrives by itself (an
  entity FIROS writes a moment after a message): each command runs again until its output is the one shown, for
  up to ``EVENTUALLY`` seconds. Only for commands that change nothing.
- ``<!-- runnable: background, port NAME -->``: a script whose last command runs until Ctrl-C (a broker, FIROS),
  which a reader starts in a terminal of its own. It is started in the background; the next block runs once
  ``127.0.0.1:$NAME`` accepts connections; when the page's examples are done it gets SIGINT (Ctrl-C) and must
  exit 0.
- ``<!-- example settings -->``: the ``export`` lines a reader pastes first. Not run (the test provides its own
  values); the names exported there must be names the test provides, and the names the page's examples use must
  be exported there (or assigned by the examples themselves).

What the examples run against (the ``platform`` fixture): ``./run demo`` itself (``demo.run_demo``: a real master
and the robot ``demo_robot`` paired, on loopback, with ports of its own), and the settings it prints for exactly
this purpose: its workspace overlay sourced, ``MASTER``, ``RCMP_HOME``, ``ROS_MASTER_URI`` and a ``PATH`` with the
clone (for ``rcmp_n``) and ``/usr/bin`` first. The terminal starts from the PATH a person has here (pyenv's python
first: the PATH trap), so the printed settings must be enough. ``BROKER_PORT`` and ``FIROS_PORT`` are free ports.
Commands run from the clone's folder, with ``TMPDIR`` in the test's folder.

Outputs: every command must exit 0. Where the page shows output it must match standard output: JSON (one
line, or the whole output) compared as data (key order free), with ``...`` in a shown string standing for any
text and the time stamps of ``VARYING_KEYS`` not compared; other lines compared as text (``...`` again any text),
in order, where the actual output may have HTTP header lines or blank lines between them (``curl -i`` prints
every header; a page shows the ones that matter). After each page, the platform's robots and service logics are
as they were before it.

Trust: the commands come from this repository's own pages and run with bash, as a reader would run them; no
input from anywhere else reaches a shell.
"""

from __future__ import annotations

import json
import os
import re
import select
import shlex
import signal
import subprocess
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from typing import List, Optional

import pytest

from tests.support.polling import wait_until
from tests.support.ports import free_port, port_accepts, stable_free_ports
from tests.support.processes import ProcessGroup, ros_env

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# the pages whose marked examples must run (one line per page)
DOCUMENTS = (
    "docs/RDAPI.md",
    "docs/FIROS.md",
    "docs/GUIDE.md",
)

VARYING_KEYS = ("firosstamp", "observedAt", "expiresAt", "notifiedAt", "modifiedAt", "createdAt")
EVENTUALLY = 30.0         # seconds an "eventually" command may take to show what the page shows
COMMAND_TIMEOUT = 60.0    # seconds one command may run
SYSTEM_PATH = "/usr/bin:/bin:/usr/sbin:/sbin"
SHELL_NAMES = {"PATH", "PWD", "HOME", "TMPDIR", "RANDOM"}

MARKER = re.compile(r"^\s*<!--\s*(runnable(?:\s*:\s*(?P<options>[^>]*?))?|example settings)\s*-->\s*$")
FENCE_OPEN = re.compile(r"^(?P<indent>\s*)```[\w-]*\s*$")
FENCE_CLOSE = re.compile(r"^\s*```\s*$")
BACKGROUND = re.compile(r"^background\s*,\s*port\s+(?P<name>[A-Z_][A-Z0-9_]*)$")
HEADER_LINE = re.compile(r"^[A-Za-z0-9-]+: ")
HEREDOC = re.compile(r"(?<!<)<<(?P<dash>-?)\s*(?P<quote>['\"]?)(?P<word>[A-Za-z_][A-Za-z0-9_]*)(?P=quote)")


# -- reading the pages ---------------------------------------------------------------------------------------------

@dataclass
class Command:
    text: str
    expected: List[str] = field(default_factory=list)


@dataclass
class Block:
    document: str
    line: int                 # of the marker, 1-based
    kind: str                 # "run", "eventually", "background", "settings"
    lines: List[str]
    port_name: Optional[str] = None

    @property
    def where(self):
        return f"{self.document}:{self.line}"

    def commands(self):
        """A terminal session's commands with the output shown for each; a script block is one command."""
        if not any(line.startswith("$ ") for line in self.lines):
            return [Command("(\nset -e\n" + "\n".join(self.lines) + "\n)")]
        commands, current = [], None
        lines = iter(self.lines)
        for line in lines:
            if line.startswith("$ "):
                text = line[2:]
                while text.endswith("\\"):
                    text += "\n" + next(lines, "")
                for heredoc in list(HEREDOC.finditer(text)):   # bash reads their lines in this order
                    text += "\n" + self.here_document(lines, heredoc)
                current = Command(text)
                commands.append(current)
            elif current is None:
                if line.strip():
                    raise ValueError(f"{self.where}: text before the first '$ ' command: {line!r}")
            else:
                current.expected.append(line)
        return commands

    def here_document(self, lines, opened):
        """The lines of the here-document ``opened`` (a match of ``HEREDOC``), its terminator line included."""
        word, body = opened.group("word"), []
        for line in lines:
            body.append(line)
            if (line.lstrip("\t") if opened.group("dash") else line) == word:
                return "\n".join(body)
        raise ValueError(f"{self.where}: the here-document <<{word} is not closed by a line '{word}'")


def read_blocks(document):
    """The marked blocks of ``document`` in page order; ValueError naming the line for a malformed one."""
    with open(os.path.join(ROOT, document), encoding="utf-8") as f:
        lines = f.read().split("\n")
    blocks = []
    for number, line in enumerate(lines):
        marker = MARKER.match(line)
        if not marker:
            if "<!--" in line and "runnable" in line:
                raise ValueError(f"{document}:{number + 1}: a runnable marker this test cannot read: {line!r}")
            continue
        where = f"{document}:{number + 1}"
        following = number + 1
        while following < len(lines) and not lines[following].strip():
            following += 1
        fence = FENCE_OPEN.match(lines[following]) if following < len(lines) else None
        if not fence:
            raise ValueError(f"{where}: the marker is not followed by a fenced block")
        indent = len(fence.group("indent"))
        body, end = [], following + 1
        while end < len(lines) and not FENCE_CLOSE.match(lines[end]):
            body.append(lines[end][indent:] if lines[end][:indent].strip() == "" else lines[end])
            end += 1
        if end == len(lines):
            raise ValueError(f"{where}: the fenced block is not closed")
        options = (marker.group("options") or "").strip()
        if marker.group(1) == "example settings":
            blocks.append(Block(document, number + 1, "settings", body))
        elif options == "":
            blocks.append(Block(document, number + 1, "run", body))
        elif options == "eventually":
            blocks.append(Block(document, number + 1, "eventually", body))
        elif BACKGROUND.match(options):
            blocks.append(Block(document, number + 1, "background", body, BACKGROUND.match(options).group("name")))
        else:
            raise ValueError(f"{where}: unknown runnable option {options!r}")
    return blocks


def exported_names(block):
    names = set()
    for line in block.lines:
        words = shlex.split(line, comments=True) if line.strip() else []
        if words[:1] == ["export"]:
            names.update(word.split("=", 1)[0] for word in words[1:] if "=" in word)
    return names


def used_and_assigned(blocks):
    used, assigned = set(), set()
    for block in blocks:
        if block.kind == "settings":
            continue
        text = "\n".join(block.lines)
        used.update(re.findall(r"\$\{?([A-Z_][A-Z0-9_]*)", text))
        assigned.update(re.findall(r"(?:^|[\s;$(])([A-Z_][A-Z0-9_]*)=", text, re.M))
    return used, assigned


# -- comparing what a command printed with what the page shows ---------------------------------------------------

def text_matches(shown, actual):
    pattern = ".*".join(re.escape(part) for part in shown.split("..."))
    return re.fullmatch(pattern, actual, re.S) is not None


def data_matches(shown, actual, key=None):
    if key in VARYING_KEYS:
        return True
    if isinstance(shown, str):
        return isinstance(actual, str) and text_matches(shown, actual)
    if isinstance(shown, dict):
        return (isinstance(actual, dict) and set(shown) == set(actual)
                and all(data_matches(shown[k], actual[k], k) for k in shown))
    if isinstance(shown, list):
        return (isinstance(actual, list) and len(shown) == len(actual)
                and all(data_matches(s, a) for s, a in zip(shown, actual)))
    return shown == actual and type(shown) is type(actual)


def as_data(text):
    text = text.strip()
    if not text.startswith(("{", "[")):
        return None
    try:
        return json.loads(text)
    except ValueError:
        return None


def line_matches(shown, actual):
    shown_data = as_data(shown)
    if shown_data is not None:
        actual_data = as_data(actual)
        return actual_data is not None and data_matches(shown_data, actual_data)
    return text_matches(shown.rstrip(), actual.rstrip())


def output_matches(expected, actual):
    """``expected``: the lines the page shows; ``actual``: the command's standard output."""
    shown = [line for line in expected if line.strip()]
    if not shown:
        return True
    whole = as_data("\n".join(shown))
    if whole is not None:
        actual_data = as_data(actual)
        return actual_data is not None and data_matches(whole, actual_data)
    lines = actual.split("\n")
    position = 0
    for line in shown:
        while position < len(lines) and not line_matches(line, lines[position]):
            if lines[position].strip() and not HEADER_LINE.match(lines[position]):
                return False
            position += 1
        if position == len(lines):
            return False
        position += 1
    return all(not rest.strip() or HEADER_LINE.match(rest) for rest in lines[position:])


# -- running them ----------------------------------------------------------------------------------------------------

class Terminal:
    """One bash, fed the commands of a block one at a time as a person types them; each command's output and exit
    status are kept in files of ``folder``."""

    def __init__(self, env, folder):
        self.folder = folder
        self.count = 0
        self.process = subprocess.Popen(["bash", "--noprofile", "--norc"], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, cwd=ROOT,
                                        start_new_session=True)
        self.seen = b""

    def run(self, text, timeout=COMMAND_TIMEOUT):
        """(exit status, stdout, stderr) of ``text`` typed into this terminal."""
        self.count += 1
        files = {part: os.path.join(self.folder, f"command-{self.count}.{part}") for part in ("out", "err", "rc")}
        done = f"__command_{self.count}_done__".encode()
        typed = (f"{{ {text}\n}} >{shlex.quote(files['out'])} 2>{shlex.quote(files['err'])} </dev/null; "
                 f"echo \"$?\" >{shlex.quote(files['rc'])}; echo {done.decode()}\n")
        self.process.stdin.write(typed.encode())
        self.process.stdin.flush()
        deadline = time.monotonic() + timeout
        while done not in self.seen:
            left = deadline - time.monotonic()
            if left <= 0:
                self.kill()
                raise AssertionError(f"{text!r} did not finish within {timeout:.0f} s")
            ready, _, _ = select.select([self.process.stdout], [], [], left)
            if ready:
                chunk = os.read(self.process.stdout.fileno(), 65536)
                if not chunk:
                    raise AssertionError(f"the shell ended while running {text!r}: {self.seen.decode()[-2000:]}")
                self.seen += chunk

        def read(part):
            with open(files[part], encoding="utf-8", errors="replace") as f:
                return f.read()
        return int(read("rc").strip()), read("out"), read("err")

    def kill(self):
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.process.wait(timeout=10)

    def close(self):
        try:
            self.process.stdin.close()
        except OSError:
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.kill()


def describe_failure(block, command, status, out, err):
    return (f"{block.where}: `{command.text}` exited {status}\n--- the page shows:\n" + "\n".join(command.expected)
            + f"\n--- it printed:\n{out}\n--- on stderr:\n{err[-3000:]}")


def run_block(block, terminal):
    for command in block.commands():
        if block.kind == "eventually":
            last = {}

            def shown_at_last():
                last["result"] = terminal.run(command.text)
                status, out, _ = last["result"]
                return status == 0 and output_matches(command.expected, out)
            try:
                wait_until(shown_at_last, timeout=EVENTUALLY, interval=0.5, message=block.where)
            except AssertionError:
                raise AssertionError(describe_failure(block, command, *last.get("result", (None, "", "")))) \
                    from None
            continue
        status, out, err = terminal.run(command.text)
        assert status == 0 and output_matches(command.expected, out), describe_failure(block, command, status,
                                                                                          out, err)


def start_background(block, env, procs):
    script = "set -e\n" + "\n".join(block.lines)
    process = procs.start(["bash", "--noprofile", "--norc", "-c", script], env=env, cwd=ROOT,
                          name=f"background-{block.line}")
    port = int(env[block.port_name])

    def listening():
        if process.poll() is not None:
            raise AssertionError(f"{block.where}: exited {process.returncode} before listening on "
                                 f"{block.port_name}={port}: {procs.output(process)[-3000:]}")
        return port_accepts(port)
    try:
        wait_until(listening, timeout=60, interval=0.2, message=f"{block.where} to listen on port {port}")
    except AssertionError as exc:
        raise AssertionError(str(exc)) from None
    return process


def stop_background(block, process, procs):
    """Ctrl-C, as a reader ends it: SIGINT to its process group; it must exit 0."""
    os.killpg(process.pid, signal.SIGINT)
    try:
        status = process.wait(timeout=30)
    except subprocess.TimeoutExpired:
        status = None
    assert status == 0, f"{block.where}: exited {status} on Ctrl-C: {procs.output(process)[-3000:]}"


# -- the platform ----------------------------------------------------------------------------------------------------

def user_path():
    """The PATH a person has on this machine: what scripts/with-overlay.sh put in front of it taken away."""
    path = os.environ.get("PATH", "")
    while path.startswith(SYSTEM_PATH + ":"):
        path = path[len(SYSTEM_PATH) + 1:]
    return path or SYSTEM_PATH


def printed_settings(text):
    """The environment that the ``source`` and ``export`` lines ./run demo printed give a terminal."""
    source = re.search(r"^  source (\S+)$", text, re.M)
    export = re.search(r"^  export (.+)$", text, re.M)
    assert source and export, text
    overlay = shlex.split(source.group(1))[0]
    assert overlay == os.path.join(ROOT, "build", "rcmp_ws", "devel", "setup.bash")
    base = {key: value for key, value in os.environ.items()
            if not key.startswith(("ROS_", "CMAKE_", "PYTHON", "LD_LIBRARY", "PKG_CONFIG", "CATKIN"))}
    base["PATH"] = user_path()
    sourced = subprocess.run(["bash", "--noprofile", "--norc", "-c", '. "$1" >/dev/null && exec env -0', "bash",
                              overlay], env=base, capture_output=True, timeout=60, check=True).stdout
    env = dict(item.decode().split("=", 1) for item in sourced.split(b"\0") if b"=" in item)
    for word in shlex.split(export.group(1)):
        name, value = word.split("=", 1)
        assert "$" not in value.replace("$PATH", ""), word
        env[name] = value.replace("$PATH", env["PATH"])
    return env, {word.split("=", 1)[0] for word in shlex.split(export.group(1))}


@pytest.fixture(scope="module")
def platform(tmp_path_factory):
    """./run demo, running, and the terminal environment its printed settings give (plus the FIROS ports)."""
    folder = tmp_path_factory.mktemp("doc-examples-demo")
    procs = ProcessGroup(log_dir=str(folder))
    try:
        port = free_port()
        demo = procs.start(["/usr/bin/python3", "-m", "demo.run_demo", "--port", str(port), "--workdir",
                            str(folder / "demo")], env=ros_env(), cwd=ROOT, name="demo")
        text = wait_until(lambda: (lambda out: out if "Press Ctrl-C" in out else None)(procs.output(demo)),
                          timeout=120, message="./run demo to say it is running")
        env, names = printed_settings(text)
        broker_port, firos_port = stable_free_ports(2)
        env.update(BROKER_PORT=str(broker_port), FIROS_PORT=str(firos_port))
        yield {"env": env, "provided": names | {"BROKER_PORT", "FIROS_PORT"},
               "base_url": f"http://127.0.0.1:{port}", "demo": demo, "procs": procs}
        os.killpg(demo.pid, signal.SIGINT)
        assert demo.wait(timeout=60) == 0
    finally:
        procs.stop_all()


def rdapi_read(base_url, path):
    with urllib.request.urlopen(base_url + path, timeout=10) as answer:
        return json.loads(answer.read())["reason"]


def platform_state(base_url):
    """The robots and service logics, once the RDAPI answers without a token (a page may have just revoked the
    last one; the master re-reads its tokens every second)."""
    def read():
        try:
            return rdapi_read(base_url, "/platform_instance/read"), rdapi_read(base_url, "/service_logic/read")
        except urllib.error.HTTPError as exc:
            if exc.code == 401:
                return None
            raise
    return wait_until(read, timeout=10, message="the RDAPI to answer without a token")


# -- the tests -------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("document", DOCUMENTS)
def test_the_page_marks_runnable_examples_readably(document):
    blocks = read_blocks(document)
    kinds = [b.kind for b in blocks]
    assert "run" in kinds or "eventually" in kinds, f"{document} has no runnable example"
    for block in blocks:
        if block.kind != "settings":
            assert block.commands(), block.where


def test_a_here_document_is_part_of_the_command_that_opens_it():
    block = Block("page.md", 1, "run", ["$ cat <<EOF", "$ not a command", "EOF", "not a command",
                                        "$ cat <<-'END' && tr a b <<<a", "\t$HOME", "\tEND", "$HOME", "b"])
    commands = block.commands()
    assert [c.text for c in commands] == ["cat <<EOF\n$ not a command\nEOF",
                                          "cat <<-'END' && tr a b <<<a\n\t$HOME\n\tEND"]
    assert [c.expected for c in commands] == [["not a command"], ["$HOME", "b"]]
    with pytest.raises(ValueError, match="not closed"):
        Block("page.md", 7, "run", ["$ cat <<EOF", "one"]).commands()


@pytest.mark.slow
@pytest.mark.parametrize("document", DOCUMENTS)
def test_the_examples_of_the_page_run_as_written(platform, document, tmp_path):
    blocks = read_blocks(document)
    provided = platform["provided"]
    settings = set().union(*[exported_names(b) for b in blocks if b.kind == "settings"])
    assert settings <= provided, f"{document} exports {sorted(settings - provided)}, which this test does not provide"
    used, assigned = used_and_assigned(blocks)
    unexplained = used - assigned - settings - SHELL_NAMES
    assert not unexplained, f"{document} uses {sorted(unexplained)} without showing where they come from"

    env = dict(platform["env"], TMPDIR=str(tmp_path), ROS_LOG_DIR=str(tmp_path / "roslog"))
    before = platform_state(platform["base_url"])
    terminal = Terminal(env, str(tmp_path))
    procs = ProcessGroup(log_dir=str(tmp_path))
    background = []
    try:
        for block in blocks:
            if block.kind == "background":
                background.append((block, start_background(block, env, procs)))
            elif block.kind in ("run", "eventually"):
                run_block(block, terminal)
        for block, process in reversed(background):
            stop_background(block, process, procs)
    finally:
        terminal.close()
        procs.stop_all()
    assert platform_state(platform["base_url"]) == before, f"{document}'s examples changed the platform"


def test_the_clones_rcmp_n_runs_with_another_python_first_on_path(tmp_path):
    """The pages' ``rcmp_n`` is the clone's (the demo's settings put the clone on PATH): it names its own
    interpreter, so a PATH whose python3 cannot see ROS, Twisted or netifaces (pyenv's, here) does not matter."""
    env = {"PATH": user_path(), "HOME": str(tmp_path), "LC_ALL": "C.UTF-8"}
    for argv in (["--help"], ["--home", str(tmp_path), "token", "list"], ["vpn", "--help"]):
        done = subprocess.run([os.path.join(ROOT, "rcmp_n"), *argv], env=env, cwd=str(tmp_path),
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, (argv, done.stderr)
        assert "Traceback" not in done.stderr
