"""Command line of the stand-in broker: ``/usr/bin/python3 -m tests.ngsi_broker --port 1026 [--host 127.0.0.1]``.

Prints ``ngsi_broker listening on http://HOST:PORT`` once it accepts connections (``--port 0`` picks a free
port and prints it), serves until SIGTERM or SIGINT, then exits 0.
"""

import argparse
import logging
import signal
import sys
import threading

from .server import MAX_BODY, BrokerServer


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="python3 -m tests.ngsi_broker",
                                     description="Stand-in FIWARE Orion context broker for tests "
                                                 "(NGSI v2, the NGSI v1 of Orion before 3.10, NGSI-LD as "
                                                 "Orion-LD).")
    parser.add_argument("--port", type=int, default=1026, help="TCP port (default 1026, 0 = any free port)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--notify-timeout", type=float, default=2.0,
                        help="seconds to wait for a notification receiver (default 2)")
    parser.add_argument("--max-body", type=int, default=MAX_BODY,
                        help=f"largest request body in bytes (default {MAX_BODY}, as Orion)")
    parser.add_argument("--no-v1-initial-notification", action="store_true",
                        help="do not send the initial notification after v1 subscribeContext "
                             "(Orion before 3.1 sent it)")
    parser.add_argument("--quiet", action="store_true", help="do not log every request")
    args = parser.parse_args(argv)
    if not 0 <= args.port <= 65535:
        parser.error(f"--port {args.port}: not a TCP port")
    if args.notify_timeout <= 0:
        parser.error("--notify-timeout must be positive")
    if args.max_body <= 0:
        parser.error("--max-body must be positive")
    return args


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        stream=sys.stderr)
    try:
        broker = BrokerServer(args.host, args.port, notify_timeout=args.notify_timeout, max_body=args.max_body,
                              v1_initial_notification=not args.no_v1_initial_notification, quiet=args.quiet)
    except OSError as exc:
        print(f"ngsi_broker: cannot listen on {args.host}:{args.port}: {exc.strerror or exc}", file=sys.stderr)
        return 1

    def stop(signum, frame):
        # shutdown() waits for serve_forever, which runs in this (main) thread: ask from another thread
        threading.Thread(target=broker.httpd.shutdown, daemon=True).start()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print(f"ngsi_broker listening on {broker.url}", flush=True)
    broker.serve_forever()
    broker.httpd.server_close()
    broker.notifier.close(timeout=0.5)
    return 0


if __name__ == "__main__":
    sys.exit(main())
