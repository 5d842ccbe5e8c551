"""The managed VPN in the agent (rcmp_vpn.ManagedVpn) with a real OpenVPN that cannot run: restarted with backoff,
logged, stopped with the agent. (Over a working VPN, across hosts: tests/system/test_vpn_hosts.py.)"""

import os
import re

from tests.support.lifecycle import processes_mentioning
from tests.support.polling import wait_until
from tests.support.rcmp_agent import RcmpAgent


def test_an_openvpn_that_keeps_exiting_is_restarted_with_backoff_and_stopped_with_the_agent(procs, tmp_path):
    home = tmp_path / "robot"
    (home / "vpn").mkdir(parents=True, mode=0o755)
    (home / "vpn" / "client.conf").write_text("client\nno-such-openvpn-option yes\n")
    os.chmod(home / "vpn" / "client.conf", 0o644)
    agent = RcmpAgent(procs, str(home), role="robot", name="robot1", vpn_address=None,
                      vpn_interface="rcmtnone0", ip_master="127.0.0.1")
    agent.start(wait=False)
    text = wait_until(lambda: (lambda t: t if "starting it again in 4 s" in t else None)(agent.log_text()),
                      timeout=30, interval=0.1, message="three OpenVPN restarts")
    delays = [float(d) for d in re.findall(r"managed VPN: OpenVPN ended \(exited with status 1 [^\n]*starting it "
                                           r"again in (\d+) s", text)]
    assert delays[:3] == [1, 2, 4], text
    assert "no-such-openvpn-option" in text          # OpenVPN's own complaint is in the log line
    assert "readable by others; making them private" in text
    assert oct(os.stat(home / "vpn").st_mode & 0o777) == "0o700"
    assert oct(os.stat(home / "vpn" / "client.conf").st_mode & 0o777) == "0o600"
    assert "waiting for the address of rcmtnone0 before starting the agent" in text
    assert "connected to master" not in text          # nothing else started before the VPN is up
    assert agent.stop() == 0
    assert "managed VPN: stopping OpenVPN" in agent.log_text()
    assert not processes_mentioning(str(home))


def test_a_master_that_cannot_start_once_its_vpn_is_up_says_why_and_stops_its_openvpn(procs, tmp_path):
    home = tmp_path / "master"
    (home / "vpn").mkdir(parents=True, mode=0o700)
    (home / "vpn" / "server.conf").write_text("no-such-openvpn-option yes\n")   # never a real tun0 here
    agent = RcmpAgent(procs, str(home), role="master", vpn_address="127.0.0.1", ext_address=None,
                      ext_interface="rcmtnone0")
    agent.start(wait=False)
    assert agent.process.wait(timeout=30) == 2
    output = agent.output()
    assert "cannot start the master" in output and "rcmtnone0" in output and "Traceback" not in output
    text = agent.log_text()
    assert "managed VPN: starting OpenVPN" in text and "managed VPN: stopping OpenVPN" in text
    assert text.index("managed VPN: starting OpenVPN") < text.index("cannot start")
    wait_until(lambda: not processes_mentioning(str(home)), timeout=10, message="OpenVPN to be gone")
