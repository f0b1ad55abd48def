"""A fork server for the docs test: imports torch and the CLI once, then runs each `boostnerf ...` call
in a forked child, so the dozens of documented commands do not each pay torch's import (seconds).

    python tests/cli_server.py SOCKET          # serve until killed
    python tests/cli_server.py --client SOCKET ARGS...   # what the `boostnerf` shim runs

The client sends its arguments, working folder and environment as JSON and its stdin, stdout and
stderr as file descriptors; the child adopts them, runs `boostnerf_cli.cli.main()` and the client
exits with the child's exit code. One command at a time (the docs run sequentially).
"""

from __future__ import annotations

import json
import os
import socket
import sys


def serve(path: str) -> None:
    import torch

    import boostnerf_cli.cli
    from boostnerf_cli.stages import (  # noqa: F401
        build_moe,
        count_params,
        evaluate,
        finetune,
        pretrain,
        render,
    )

    torch.set_num_threads(1)
    torch.optim.Adam([torch.zeros(1, requires_grad=True)], fused=True)  # loads the optimiser's lazy imports
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(1)
    print("ready", flush=True)
    while True:
        conn, _ = srv.accept()
        msg, fds, _, _ = socket.recv_fds(conn, 1 << 20, 3)
        request = json.loads(msg.decode())
        pid = os.fork()
        if pid == 0:
            srv.close()
            for target, fd in enumerate(fds):
                os.dup2(fd, target)
            os.chdir(request["cwd"])
            os.environ.clear()
            os.environ.update(request["env"])
            sys.argv = ["boostnerf", *request["args"]]
            code = 0
            try:
                boostnerf_cli.cli.main()
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
            except BaseException:  # noqa: BLE001  (report any crash as a failed command)
                import traceback

                traceback.print_exc()
                code = 1
            sys.stdout.flush()
            sys.stderr.flush()
            conn.sendall(str(code).encode())
            os._exit(code)
        for fd in fds:
            os.close(fd)
        os.waitpid(pid, 0)
        conn.close()


def client(path: str, args: list[str]) -> int:
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    conn.connect(path)
    request = json.dumps({"args": args, "cwd": os.getcwd(), "env": dict(os.environ)}).encode()
    socket.send_fds(conn, [request], [0, 1, 2])
    reply = conn.recv(16)
    return int(reply or b"1")


if __name__ == "__main__":
    if sys.argv[1] == "--client":
        sys.exit(client(sys.argv[2], sys.argv[3:]))
    serve(sys.argv[1])
