"""sub_inst.sh, the installer the zips ship: its list of ROS packages is the one development installs."""

import os

from tests.support.paths import REPO


def _bash_words(text, start, end):
    block = text.split(start, 1)[1].split(end, 1)[0]
    if start.startswith("#"):  # a comment line opens the block: the words start on the next line
        block = block.split("\n", 1)[1]
    return {w for line in block.splitlines() for w in line.split("#", 1)[0].split()}


def test_installer_installs_the_ros_packages_development_uses():
    """sub_inst.sh's ROS list (shipped in the zips) must not drift from scripts/install-deps.sh's."""
    with open(os.path.join(REPO, "scripts", "install-deps.sh")) as f:
        dev = _bash_words(f.read(), "# ROS 1", "# the agent")
    with open(os.path.join(REPO, "sub_inst.sh")) as f:
        text = f.read()
    shipped = _bash_words(text, "ROS_PACKAGES=(", ")")
    agent = _bash_words(text, "AGENT_PACKAGES=(", ")") | _bash_words(text, "MASTER_PACKAGES=(", ")")
    assert dev and dev <= shipped, f"missing from sub_inst.sh: {sorted(dev - shipped)}"
    assert {"python3-twisted", "python3-netifaces", "openvpn", "sqlite3"} <= agent
