"""`make demo`: bring up the platform's main job on this one machine and leave it running until Ctrl-C.

It starts an RCM master on 127.0.0.1 (RDAPI on ``--port``, default 8080 or the next free port) and a robot agent
named ``demo_robot`` on 127.0.0.2, both as real ``python3 -m rcm_platform`` agents with their own platform
folders under ``--workdir``; provisions the ``demo_patrol`` service logic (the simulated robot ``sim_robot`` on
the robot side, the ``patrol_brain`` that steers it on the server side) and the robot; waits until the robot is
``paired``; then prints the original FIWARE Robotics guide's curl commands with the right address and the
console's address. Ctrl-C (or SIGTERM) stops the robot agent, then the master, and checks that each agent's
process group is gone.
"""

import argparse
import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MASTER_ADDRESS = "127.0.0.1"
ROBOT_ADDRESS = "127.0.0.2"
ROBOT_NAME = "demo_robot"
SERVICE_LOGIC = {
    "slg_name": "demo_patrol",
    "sn_list": [
        {"sn_package": "robotics_demo", "sn_type": "sim_robot.py", "sn_name": "sim_robot",
         "sn_params": "", "sn_side": "R"},
        {"sn_package": "robotics_demo", "sn_type": "patrol_brain.py", "sn_name": "patrol_brain",
         "sn_params": "_speed:=0.5 _radius:=2.0", "sn_side": "S"},
    ],
    "sl_list": [],
}


class DemoError(Exception):
    """Something the person running the demo must fix; printed as one line."""


def port_is_free(address, port):
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((address, port))
            return True
        except OSError:
            return False


def first_free_port(address, preferred):
    for port in range(preferred, preferred + 100):
        if port_is_free(address, port):
            return port
    raise DemoError(f"no free port on {address} from {preferred} to {preferred + 99}")


def write_config(home, filename, values):
    os.makedirs(home, exist_ok=True)
    lines = ["[main]"] + [f"{key}={value}" for key, value in values.items()]
    with open(os.path.join(home, filename), "w") as f:
        f.write("\n".join(lines) + "\n")


def agent_env():
    env = dict(os.environ)
    env["PATH"] = "/usr/bin:/bin:/usr/sbin:/sbin:" + env.get("PATH", "")
    env["PYTHONPATH"] = ROOT + (":" + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def start_agent(home, log_name):
    log = open(os.path.join(home, log_name), "ab")
    try:
        return subprocess.Popen(["/usr/bin/python3", "-m", "rcm_platform", "--home", home],
                                env=agent_env(), cwd=ROOT, stdin=subprocess.DEVNULL, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
    finally:
        log.close()


def stop_agent(proc, name, timeout=30.0):
    """SIGTERM the agent (it stops everything it started), escalate to SIGKILL of its group if it hangs."""
    if proc is None:
        return
    for sig, wait in ((signal.SIGTERM, timeout), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=wait)
            break
        except subprocess.TimeoutExpired:
            print(f"demo: {name} did not stop within {wait:.0f} s, sending SIGKILL", file=sys.stderr)
    try:
        os.killpg(proc.pid, 0)
        print(f"demo: processes of {name} (group {proc.pid}) are still running", file=sys.stderr)
    except ProcessLookupError:
        pass


def call(base_url, path, body=None, timeout=5.0):
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(base_url + path, data=data,
                                     headers={"Content-Type": "application/json"} if data else {})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            raw = response.read()
    except urllib.error.HTTPError as exc:
        raw = exc.read()
    try:
        return json.loads(raw)
    except ValueError:
        return {"result": "HTML", "reason": raw.decode("utf-8", "replace")}


def wait_for(what, condition, timeout, agents):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for name, proc, home in agents:
            if proc.poll() is not None:
                raise DemoError(f"the {name} agent exited with status {proc.returncode}; "
                                f"see {os.path.join(home, 'log', 'rcmp.log')}")
        try:
            value = condition()
        except OSError:
            value = None
        if value:
            return value
        time.sleep(0.2)  # polling interval
    raise DemoError(f"timed out after {timeout:.0f} s waiting for {what}")


def console_link(base_url, robot, topic="/pose"):
    """The console's page of ``robot`` with ``topic`` drawn (the page takes the topic from its address)."""
    return f"{base_url}/console/#/robot/{robot}?topic={topic}"


def example_settings(host, master_home, ros_master_uri):
    """The lines that let the examples of docs/GUIDE.md, docs/RDAPI.md and docs/FIROS.md run as they are written,
    against this demo, from this clone: the workspace overlay (firos, rcm, robotics_msgs, robotics_demo),
    ``MASTER`` (the RDAPI's address), ``RCMP_HOME`` (the master's platform folder, for ``rcmp_n token``),
    ``ROS_MASTER_URI`` (the robot's service space) and a PATH that finds this clone's ``rcmp_n`` and the system's
    ``python3`` (ROS's)."""
    overlay = os.path.join(ROOT, "build", "rcmp_ws", "devel", "setup.bash")
    exports = {"MASTER": host, "RCMP_HOME": master_home, "ROS_MASTER_URI": ros_master_uri}
    words = " ".join(f"{key}={shlex.quote(value)}" for key, value in exports.items())
    return [f"source {shlex.quote(overlay)}", f"export {words} PATH={shlex.quote(ROOT)}:/usr/bin:$PATH"]


def describe(base_url, master_home, robot_home):
    host = base_url[len("http://"):]
    space = call(base_url, f"/service_space/read?ss_name={ROBOT_NAME}").get("reason", {})
    uri = space.get("ros_master_uri", "") if isinstance(space, dict) else ""
    settings = "\n".join("  " + line for line in example_settings(host, master_home, uri or "http://127.0.0.1:11311/"))
    print(f"""
The demo is running: master RDAPI at {base_url}, robot '{ROBOT_NAME}' on {ROBOT_ADDRESS}, paired.
Look around with the original FIWARE Robotics guide's commands (public_ip_master is {host}; docs/GUIDE.md):

  curl http://{host}
  curl http://{host}/platform_instance/read
  curl http://{host}/service_logic/read
  curl http://{host}/service_logic/read?slg_name={SERVICE_LOGIC['slg_name']}
  curl "http://{host}/service_space/read?ss_name={ROBOT_NAME}"

Watch the platform and the robot circle in a browser, live (the console, on the robot's /pose):

  Console: {console_link(base_url, ROBOT_NAME)}

The robot's service space is a ROS master of its own{(' at ' + uri) if uri else ''}; on the command line:

  PATH=/usr/bin:$PATH ROS_MASTER_URI={uri or 'http://127.0.0.1:<port>/'} rostopic echo /pose

To run the examples of docs/GUIDE.md, docs/RDAPI.md and docs/FIROS.md as they are written, first paste in
another terminal:

{settings}

Logs: {os.path.join(master_home, 'log')} (master) and {os.path.join(robot_home, 'log')} (robot).
Press Ctrl-C to stop everything.
""", flush=True)


def run(args):
    workdir = os.path.abspath(args.workdir)
    master_home = os.path.join(workdir, "master")
    robot_home = os.path.join(workdir, "robot")
    for home in (master_home, robot_home):
        if os.path.isdir(home):
            shutil.rmtree(home)
    port = args.port if args.port else first_free_port(MASTER_ADDRESS, 8080)
    if not port_is_free(MASTER_ADDRESS, port):
        raise DemoError(f"port {port} on {MASTER_ADDRESS} is in use; choose another with --port")
    ic_port = first_free_port(MASTER_ADDRESS, 9999)
    write_config(master_home, ".init.cfg", {
        "inbound_open_ports": "10100, 10101, 10102, 10103", "ext_address": MASTER_ADDRESS, "ext_port": port,
        "vpn_address": MASTER_ADDRESS, "ic_port": ic_port, "ros_port_base": first_free_port(MASTER_ADDRESS, 11411)})
    write_config(robot_home, "init.cfg", {
        "name": ROBOT_NAME, "robot": "yes", "ip_master": MASTER_ADDRESS, "vpn_address": ROBOT_ADDRESS,
        "ic_port": ic_port})
    base_url = f"http://{MASTER_ADDRESS}:{port}"
    master = robot = None
    try:
        print(f"demo: starting the master (RDAPI {base_url}, platform address {MASTER_ADDRESS}:{ic_port})", flush=True)
        master = start_agent(master_home, "agent.out")
        agents = [("master", master, master_home)]
        wait_for("the master's RDAPI", lambda: call(base_url, "/platform_instance/read").get("result") == "OK",
                 30, agents)
        for path, body in (("/service_logic/provisioning", SERVICE_LOGIC),
                           ("/platform_instance/provisioning",
                            {"pi_name": ROBOT_NAME, "pi_service_logic": SERVICE_LOGIC["slg_name"]})):
            answer = call(base_url, path, body)
            print(f"demo: POST {path} -> {answer.get('result')}: {answer.get('reason')}", flush=True)
            if answer.get("result") != "OK":
                raise DemoError(f"provisioning failed: {answer.get('reason')}")
        print(f"demo: starting the robot agent '{ROBOT_NAME}' on {ROBOT_ADDRESS}", flush=True)
        robot = start_agent(robot_home, "agent.out")
        agents.append(("robot", robot, robot_home))

        def paired():
            rows = call(base_url, "/platform_instance/read").get("reason", [])
            return any(r.get("pi_name") == ROBOT_NAME and r.get("paired") for r in rows)
        wait_for(f"'{ROBOT_NAME}' to be paired", paired, args.timeout, agents)
        describe(base_url, master_home, robot_home)
        if args.exit_when_paired:
            return 0
        stop = {"now": False}
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.update(now=True))
        while not stop["now"]:
            for name, proc, home in agents:
                if proc.poll() is not None:
                    raise DemoError(f"the {name} agent exited with status {proc.returncode}; "
                                    f"see {os.path.join(home, 'log', 'rcmp.log')}")
            time.sleep(0.5)  # waiting for Ctrl-C
        print("\ndemo: stopping the robot agent, then the master", flush=True)
        return 0
    finally:
        stop_agent(robot, "robot agent")
        stop_agent(master, "master")
        print("demo: stopped", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(prog="make demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--port", type=int, default=int(os.environ.get("DEMO_PORT", "0")),
                        help="RDAPI port on 127.0.0.1 (default: 8080 or the next free one; env DEMO_PORT)")
    parser.add_argument("--workdir", default=os.path.join(ROOT, "build", "demo"),
                        help="where the two agents' platform folders go (default: build/demo)")
    parser.add_argument("--timeout", type=float, default=90.0, help="seconds to wait for pairing (default 90)")
    parser.add_argument("--exit-when-paired", action="store_true",
                        help="stop everything as soon as the robot is paired (used by the tests)")
    args = parser.parse_args(argv)
    try:
        return run(args)
    except DemoError as exc:
        print(f"demo: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
