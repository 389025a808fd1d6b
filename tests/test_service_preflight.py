"""``swarmvo serve`` refuses what cannot work before it starts, in one line: the data folder,
the address, the database (reachable, supported, its password never printed)."""

from __future__ import annotations

import socket

import pytest

from estimator.cli.main import main
from service.preflight import check_database, check_listen, prepare_data_dir


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    lines = [line for line in err.splitlines() if "warning" not in line]
    assert len(lines) == 1, err
    assert lines[0].startswith("swarmvo serve: error: "), err
    return lines[0]


def test_a_data_directory_that_is_a_file_is_refused(tmp_path, capsys):
    taken = tmp_path / "data"
    taken.write_text("")
    with pytest.raises(ValueError, match="is a file, not a folder"):
        prepare_data_dir(taken)
    assert main(["serve", "--open", "--data-dir", str(taken)]) == 2
    assert str(taken) in _one_line_error(capsys)
    prepare_data_dir(tmp_path / "new" / "data")  # made, parents and all
    assert (tmp_path / "new" / "data").is_dir()


def test_a_taken_port_is_refused_before_anything_starts(tmp_path, capsys):
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        with pytest.raises(ValueError, match="in use"):
            check_listen("127.0.0.1", port)
        assert main(["serve", "--open", "--port", str(port),
                     "--data-dir", str(tmp_path)]) == 2
        assert f"127.0.0.1:{port}" in _one_line_error(capsys)
    check_listen("127.0.0.1", port)  # free again
    with pytest.raises(ValueError, match=r"cannot listen on no-such-host\.invalid"):
        check_listen("no-such-host.invalid", 8000)


def test_unsupported_database_urls_are_refused_without_their_password(tmp_path, capsys):
    for url in ("mysql://robot:hunter2@db/odometry", "not a url at all"):
        assert main(["serve", "--open", "--data-dir", str(tmp_path),
                     "--database-url", url]) == 2
        line = _one_line_error(capsys)
        assert "database_url" in line and "sqlite:///PATH" in line, line
        assert "hunter2" not in line


def test_a_database_that_is_away_is_one_line_with_the_password_hidden(tmp_path, capsys):
    with socket.socket() as closed:  # a port nobody listens on
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    url = f"postgresql://robot:hunter2@127.0.0.1:{port}/odometry"
    with pytest.raises(ValueError, match="cannot open the database") as refused:
        check_database(url)
    assert "hunter2" not in str(refused.value) and "robot:***@" in str(refused.value)
    assert main(["serve", "--open", "--port", "0", "--data-dir", str(tmp_path),
                 "--database-url", url]) == 2
    line = _one_line_error(capsys)
    assert "hunter2" not in line and f"127.0.0.1:{port}" in line


def test_sqlite_folders_are_made_and_a_file_in_the_way_is_named(tmp_path):
    check_database(f"sqlite:///{tmp_path / 'a' / 'b' / 'poses.sqlite3'}")
    assert (tmp_path / "a" / "b" / "poses.sqlite3").exists()
    (tmp_path / "blocked").write_text("")
    with pytest.raises(ValueError, match="cannot open the database sqlite:///"):
        check_database(f"sqlite:///{tmp_path / 'blocked' / 'poses.sqlite3'}")


def test_a_driver_that_is_not_there_is_named(tmp_path, capsys):
    url = "postgresql+nosuchdriver://robot:hunter2@127.0.0.1/odometry"
    with pytest.raises(ValueError, match="driver 'nosuchdriver' is not installed") as refused:
        check_database(url)
    assert "hunter2" not in str(refused.value)
    # A SQLite URL naming its driver is still a file whose folder is made.
    check_database(f"sqlite+pysqlite:///{tmp_path / 'made' / 'poses.sqlite3'}")
    assert (tmp_path / "made" / "poses.sqlite3").exists()
