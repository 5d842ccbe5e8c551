"""rcmp_node: the agent's own files (older world-readable logs and data tightened)."""

import os

from rcm_platform import rcmp_node


def test_tighten_files_takes_others_off_old_logs_and_data(tmp_path):
    (tmp_path / "log").mkdir(mode=0o755)
    (tmp_path / "log" / "rcmp.log").write_text("x")
    (tmp_path / "robotics_data.db").write_text("x")
    for path in (tmp_path / "log" / "rcmp.log", tmp_path / "robotics_data.db"):
        os.chmod(path, 0o666)
    os.chmod(tmp_path / "log", 0o777)
    rcmp_node.tighten_files(str(tmp_path))
    assert oct(os.stat(tmp_path / "log").st_mode & 0o777) == "0o750"
    assert oct(os.stat(tmp_path / "log" / "rcmp.log").st_mode & 0o777) == "0o640"
    assert oct(os.stat(tmp_path / "robotics_data.db").st_mode & 0o777) == "0o640"
