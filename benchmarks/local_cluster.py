"""Real processes on loopback for the fleet harness and its tests: PostgreSQL, replicas, nginx.

- :class:`Postgres`: a throwaway cluster from Debian's server binaries (initdb + pg_ctl) in a
  temporary folder, run as the ``postgres`` user when we are root;
- :class:`Replica`: one service process (uvicorn, worker processes) on its own port, killed
  with SIGKILL or paused with SIGSTOP as the harness says;
- :class:`Balancer`: nginx with ``docker/nginx.conf`` (the configuration compose ships), only
  its upstream list and port replaced.

:func:`missing_tools` says what is absent, so callers skip with that reason.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

PROJECT_ROOT = Path(__file__).resolve().parents[1]
NGINX_CONF = PROJECT_ROOT / "docker" / "nginx.conf"
DB_USER = "swarmvo"
# Starts one replica: every setting comes from SWARMVO_* variables.
REPLICA_CODE = (
    "import sys\nfrom service.server import serve\nfrom service.settings import ServiceSettings\n"
    "sys.exit(serve(ServiceSettings(), 'warning'))\n"
)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def postgres_binaries() -> Path | None:
    """Folder with initdb and pg_ctl: Debian's newest /usr/lib/postgresql/N/bin, else PATH."""
    folders = sorted(
        (Path(p).parent for p in glob.glob("/usr/lib/postgresql/*/bin/pg_ctl")),
        key=lambda folder: int(folder.parent.name) if folder.parent.name.isdigit() else 0,
    )
    if folders and (folders[-1] / "initdb").exists():
        return folders[-1]
    pg_ctl = shutil.which("pg_ctl")
    if pg_ctl and (Path(pg_ctl).parent / "initdb").exists():
        return Path(pg_ctl).parent
    return None


def missing_tools() -> str | None:
    """Why the cluster cannot run here (None: it can)."""
    if shutil.which("nginx") is None and not Path("/usr/sbin/nginx").exists():
        return "nginx is not installed (Debian: apt-get install nginx)"
    if postgres_binaries() is None:
        return ("no PostgreSQL server binaries (initdb, pg_ctl) in /usr/lib/postgresql/*/bin "
                "or on PATH (Debian: apt-get install postgresql)")
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            return "running as root, and there is no 'postgres' user to run PostgreSQL as"
        if shutil.which("runuser") is None:
            return "running as root, and runuser (util-linux) is missing"
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "the PostgreSQL driver is missing: pip install -e '.[postgres]'"
    return None


def process_alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state != "Z"


class Postgres:
    """A private PostgreSQL cluster: own data folder, socket folder and port; fsync off.

    PostgreSQL refuses to run as root, so as root every server command runs as the
    unprivileged ``postgres`` user (which Debian's package creates). ``settings`` are extra
    server settings (``-c name=value``).
    """

    def __init__(self, settings: dict[str, str] | None = None) -> None:
        self.settings = {"max_connections": "200", **(settings or {})}
        binaries = postgres_binaries()
        if binaries is None:
            raise RuntimeError(missing_tools() or "no PostgreSQL binaries")
        self.binaries = binaries
        self.prefix: list[str] = []
        self.root = Path(tempfile.mkdtemp(prefix="swarmvo-pg-"))
        if os.geteuid() == 0:
            account = pwd.getpwnam("postgres")
            os.chown(self.root, account.pw_uid, account.pw_gid)
            self.prefix = ["runuser", "-u", "postgres", "--"]
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self.port = free_port()
        self.postmaster: int | None = None
        try:
            self._run("initdb", "-D", str(self.data), "-U", DB_USER, "--auth=trust", "-E",
                      "UTF8", "--locale=C", "--no-sync")
            self.start()
        except BaseException:
            self.remove()
            raise

    def _run(self, program: str, *args: str) -> None:
        command = [*self.prefix, str(self.binaries / program), *args]
        finished = subprocess.run(command, capture_output=True, text=True, timeout=60,
                                  cwd=self.root)
        if finished.returncode != 0:
            log = self.log.read_text() if self.log.exists() else ""
            raise RuntimeError(f"{program} failed:\n{finished.stdout}{finished.stderr}{log}")

    def start(self) -> None:
        # fsync off: the data of a throwaway cluster need not survive a power cut of this
        # machine, and it runs several times faster; the socket stays in our folder.
        extra = " ".join(f"-c {name}={value}" for name, value in self.settings.items())
        options = (f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 "
                   f"-c fsync=off {extra}")
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "30",
                  "-o", options, "start")
        self.postmaster = int((self.data / "postmaster.pid").read_text().split()[0])

    def stop(self) -> None:
        """Fast shutdown (connections are cut, as when the database host goes away)."""
        if not (self.data / "postmaster.pid").exists() and self.postmaster is None:
            return
        with contextlib.suppress(RuntimeError, subprocess.TimeoutExpired):
            self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "30", "stop")
        if self.postmaster is not None and process_alive(self.postmaster):
            os.kill(self.postmaster, signal.SIGQUIT)  # immediate shutdown of all backends
            deadline = time.monotonic() + 10
            while process_alive(self.postmaster) and time.monotonic() < deadline:
                time.sleep(0.05)

    def restart(self) -> None:
        self.stop()
        self.start()

    def remove(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://{DB_USER}@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str) -> str:
        self.admin(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        self.admin(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def admin(self, sql: str) -> list[tuple]:
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user=DB_USER, dbname="postgres",
                             autocommit=True) as connection:
            cursor = connection.execute(sql)
            return cursor.fetchall() if cursor.description else []

    def query(self, database: str, sql: str, *params: object) -> list[tuple]:
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user=DB_USER,
                             dbname=database) as connection:
            return connection.execute(sql, params or None).fetchall()


class Replica:
    """One service process on ``port``; the same port again after a restart."""

    def __init__(self, name: str, database_url: str, api_key: str, folder: Path,
                 workers: int = 1, lease_ttl_s: float = 0.5, leases: bool = True) -> None:
        self.name = name
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.folder = folder
        self.log = folder / f"{name}.log"
        self.env = {
            **os.environ, "OMP_NUM_THREADS": "1", "SWARMVO_API_KEYS": api_key,
            "SWARMVO_DATABASE_URL": database_url, "SWARMVO_WORKERS": str(workers),
            "SWARMVO_HOST": "127.0.0.1", "SWARMVO_PORT": str(self.port),
            "SWARMVO_DATA_DIR": str(folder / name), "SWARMVO_LEASE_TTL_S": str(lease_ttl_s),
            "SWARMVO_LEASES": "true" if leases else "false",
        }
        self.process: subprocess.Popen | None = None
        self.generation = 0  # restarts so far: the replica id names each life

    @property
    def replica_id(self) -> str:
        return f"{self.name}.{self.generation}"

    def start(self, wait: bool = True) -> None:
        env = {**self.env, "SWARMVO_REPLICA_ID": self.replica_id}
        with self.log.open("ab") as log:
            self.process = subprocess.Popen([sys.executable, "-c", REPLICA_CODE],
                                            cwd=PROJECT_ROOT, env=env, stdout=log,
                                            stderr=subprocess.STDOUT)
        if wait:
            self.wait_healthy()

    def wait_healthy(self, timeout_s: float = 300.0) -> None:
        assert self.process is not None
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"replica {self.name} exited:\n{self.log.read_text()[-3000:]}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    return
            time.sleep(0.2)
        raise RuntimeError(f"replica {self.name} not healthy in {timeout_s:.0f} s")

    def kill(self) -> None:
        """SIGKILL: nothing is flushed, no lease is given back (a crashed machine)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=30)
        self.generation += 1

    def pause(self) -> None:
        assert self.process is not None
        self.process.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        assert self.process is not None
        self.process.send_signal(signal.SIGCONT)

    def stop(self) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGCONT)
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(timeout=30)

    def cpu_seconds(self) -> float:
        """CPU time of the replica and its worker processes (alive ones), from /proc."""
        if self.process is None or self.process.poll() is not None:
            return 0.0
        pids = [self.process.pid]
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{self.process.pid}/task").iterdir():
                pids += [int(p) for p in (task / "children").read_text().split()]
        ticks = os.sysconf("SC_CLK_TCK")
        total = 0.0
        for pid in pids:
            with contextlib.suppress(OSError, IndexError, ValueError):
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                total += (int(fields[11]) + int(fields[12])) / ticks
        return total


def nginx_config(template: str, listen_port: int, upstreams: list[str]) -> str:
    """``docker/nginx.conf`` with this machine's upstream servers and port."""
    servers = "".join(f"        server {u} max_fails=1 fail_timeout=2s;\n" for u in upstreams)
    text, count = re.subn(r"(?m)^[ \t]*server [^\n]*# upstream servers\n", lambda _m: servers,
                          template)
    text, listened = re.subn(r"(?m)^([ \t]*)listen \d+;",
                             lambda m: f"{m.group(1)}listen 127.0.0.1:{listen_port};", text)
    if count != 1 or listened != 1:
        raise ValueError("docker/nginx.conf: no '# upstream servers' line or no listen line")
    return text


class Balancer:
    """nginx in front of the replicas, with the configuration docker/ ships."""

    def __init__(self, upstreams: list[str], folder: Path) -> None:
        self.folder = folder / "nginx"
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / "logs").mkdir(exist_ok=True)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.conf = self.folder / "nginx.conf"
        self.process: subprocess.Popen | None = None
        self.configure(upstreams)

    def configure(self, upstreams: list[str]) -> None:
        self.conf.write_text(nginx_config(NGINX_CONF.read_text(), self.port, upstreams))

    def start(self) -> None:
        nginx = shutil.which("nginx") or "/usr/sbin/nginx"
        directives = f"daemon off; pid {self.folder / 'nginx.pid'}; error_log stderr warn;"
        self.process = subprocess.Popen(
            [nginx, "-p", str(self.folder), "-c", str(self.conf), "-g", directives],
            stdout=subprocess.DEVNULL, stderr=(self.folder / "error.log").open("ab"),
        )
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"nginx exited:\n{(self.folder / 'error.log').read_text()}")
            with contextlib.suppress(OSError), socket.create_connection(
                ("127.0.0.1", self.port), timeout=0.5
            ):
                return
            time.sleep(0.1)
        raise RuntimeError("nginx did not listen in 15 s")

    def reload(self, upstreams: list[str]) -> None:
        """New upstream list, gracefully (SIGHUP: open connections finish on old workers)."""
        self.configure(upstreams)
        assert self.process is not None
        self.process.send_signal(signal.SIGHUP)
        time.sleep(0.5)

    def stop(self) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGQUIT)
        try:
            self.process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(timeout=15)
