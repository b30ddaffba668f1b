"""A second process for the demo backend tests (not collected by pytest), and :class:`Peer`,
the tests' handle on it.

Speaks JSON lines: one command per line on stdin, one reply per line on stdout. On start it prints
``{"ready": true, "pid": ..., "metadata": ...}``. Commands:

- ``{"cmd": "discover", "metadata": M}``: the peer endpoint is now the process advertising M.
- ``{"cmd": "expect_publisher", "metadata": M, "gid": G}``: discovery shows publisher G (hex)
  of the process advertising M as buffer-aware and matched: that process may hand this one
  segments. At start the process that started this one is expected so (its metadata in
  ``RBPY_TEST_PUBLISHER_METADATA``), as publisher :data:`PUBLISHER_GID`.
- ``{"cmd": "publish", "n": N, "fill": B, "keep": K}``: allocate N bytes, fill them with B,
  describe them for the peer endpoint; keep the buffer under key K (or drop it when K is null).
  Reply ``{"desc": hex, "segment": [pid, id], "gen": generation, "in_shm": bool, "gone": bool}``.
- ``{"cmd": "take", "desc": hex, "key": K}``: turn a descriptor into a buffer held under key K.
  Reply ``{"ok": true, "sha": ..., "readonly": ..., "write_rejected": ...}`` or
  ``{"ok": false, "error": message}``.
- ``{"cmd": "take_drop", "descs": [hex...]}``: take and release each; reply their digests.
- ``{"cmd": "attack", "key": K}``: try to shrink, grow, write and punch a hole in the segment
  of the buffer held under K through this process's descriptor of it; reply each errno name
  (or "accepted") and the buffer's digest afterwards.
- ``{"cmd": "memory"}``: ``{"maps": memfd mappings in /proc/self/maps, "fds": memfd
  descriptors in /proc/self/fd}``.
- ``{"cmd": "orphan_seconds", "value": S}``: set ``limits.ORPHAN_SECONDS``.
- ``{"cmd": "sha", "key": K}``, ``{"cmd": "drop", "key": K}``, ``{"cmd": "stats"}``,
  ``{"cmd": "sweep"}``, ``{"cmd": "exit"}`` (a normal exit, running atexit handlers).
"""
import ctypes
import errno
import gc
import hashlib
import json
import os
import signal
import subprocess
import sys

import numpy

from rosidl_buffer_py import EndpointInfo, EndpointKind
from rosidl_buffer_py.backend import EndpointGone

import demo_buffer_backend
from demo_buffer_backend import DemoBackend, DemoBuffer, limits

#: The GID both sides use for "the other endpoint".
PEER_GID = bytes(range(16))
#: The GID of the publisher (of the process that started this one) that the peer expects.
PUBLISHER_GID = bytes(range(16, 32))
#: Environment variable: the metadata of the process that starts a peer.
PUBLISHER_METADATA = 'RBPY_TEST_PUBLISHER_METADATA'


class Peer:
    """This script running in another process, driven over JSON lines: ``peer('take', ...)``."""

    def __init__(self, capture_stderr=False):
        """With ``capture_stderr``, its log is read by :meth:`exit` into ``self.log``."""
        env = dict(os.environ, **{PUBLISHER_METADATA: DemoBackend().get_backend_metadata()})
        self.proc = subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, bufsize=1, env=env,
                                     stderr=subprocess.PIPE if capture_stderr else None)
        self.log = None
        hello = self._read()
        assert hello['ready'], hello
        self.pid = hello['pid']
        self.metadata = hello['metadata']

    def _read(self):
        line = self.proc.stdout.readline()
        assert line, f'peer exited with {self.proc.poll()}'
        return json.loads(line)

    def __call__(self, cmd, **kwargs):
        self.proc.stdin.write(json.dumps(dict(cmd=cmd, **kwargs)) + '\n')
        self.proc.stdin.flush()
        return self._read()

    def kill9(self):
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=30)

    def exit(self):
        assert self('exit')['ok']
        assert self.proc.wait(timeout=30) == 0
        if self.proc.stderr is not None:
            self.log = self.proc.stderr.read()

    def reap(self):
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=30)
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


def _sha(buf) -> str:
    return hashlib.sha256(memoryview(buf)).hexdigest()


def memfd_usage() -> dict:
    """This process's memfd mappings and descriptors (what must be gone once it drops all)."""
    with open('/proc/self/maps') as f:
        maps = sum(1 for line in f if '/memfd:' in line)
    fds = 0
    for name in os.listdir('/proc/self/fd'):
        try:
            fds += os.readlink(f'/proc/self/fd/{name}').startswith('/memfd:')
        except OSError:
            pass
    return {'maps': maps, 'fds': fds}


def _attack(buf) -> dict:
    """Try to change the size or bytes of ``buf``'s segment behind its readers' backs, through
    the descriptor this process received (read-only) and through a read-write reopening of it
    (``<name>_rw``)."""
    received = buf.hold.mapping.received.fd
    size = os.fstat(received).st_size
    libc = ctypes.CDLL(None, use_errno=True)
    results = {}

    def punch(fd):
        if libc.fallocate(fd, 3, ctypes.c_long(0), ctypes.c_long(size)) != 0:  # PUNCH|KEEP
            raise OSError(ctypes.get_errno(), 'fallocate')
    actions = {'shrink': lambda fd: os.ftruncate(fd, 4096),
               'grow': lambda fd: os.ftruncate(fd, size * 2),
               'write': lambda fd: os.pwrite(fd, b'x', 4096),
               'punch_hole': punch}
    rw = os.open(f'/proc/self/fd/{received}', os.O_RDWR)
    try:
        for suffix, fd in (('', received), ('_rw', rw)):
            for name, action in actions.items():
                try:
                    action(fd)
                    results[name + suffix] = 'accepted'
                except OSError as exc:
                    results[name + suffix] = errno.errorcode.get(exc.errno, str(exc.errno))
    finally:
        os.close(rw)
    results['size_after'] = os.fstat(received).st_size
    results['sha'] = _sha(buf)
    return results


def main() -> int:
    backend = DemoBackend()
    peer = EndpointInfo(PEER_GID, '/demo_backend_test', EndpointKind.SUBSCRIPTION)
    backend.on_discovering_endpoint(peer, [], {'demo': backend.get_backend_metadata()})
    held = {}

    def expect_publisher(gid: bytes, metadata: str) -> bool:
        info = EndpointInfo(gid, '/demo_backend_test', EndpointKind.PUBLISHER)
        return backend.on_discovering_endpoint(info, [], {'demo': metadata})[0]

    if os.environ.get(PUBLISHER_METADATA):
        expect_publisher(PUBLISHER_GID, os.environ[PUBLISHER_METADATA])

    def reply(obj):
        sys.stdout.write(json.dumps(obj) + '\n')
        sys.stdout.flush()

    reply({'ready': True, 'pid': os.getpid(), 'metadata': backend.get_backend_metadata()})
    for line in sys.stdin:
        request = json.loads(line)
        cmd = request['cmd']
        if cmd == 'publish':
            buf = DemoBuffer.allocate(request['n'])
            numpy.asarray(buf)[:] = request['fill']
            try:
                desc, gone = backend.create_descriptor_with_endpoint(buf, peer), False
            except EndpointGone:
                desc, gone = None, True
            if request.get('keep') is not None:
                held[request['keep']] = buf
            reply({'desc': desc.hex() if desc else None, 'segment': buf.segment,
                   'gen': buf.generation, 'in_shm': buf.in_shm, 'gone': gone})
        elif cmd == 'discover':
            reply({'compatible': backend.on_discovering_endpoint(
                peer, [], {'demo': request['metadata']})[0]})
        elif cmd == 'expect_publisher':
            reply({'compatible': expect_publisher(bytes.fromhex(request['gid']),
                                                  request['metadata'])})
        elif cmd == 'attack':
            reply(_attack(held[request['key']]))
        elif cmd == 'memory':
            reply(memfd_usage())
        elif cmd == 'orphan_seconds':
            limits.ORPHAN_SECONDS = request['value']
            reply({'ok': True})
        elif cmd == 'take':
            try:
                buf = backend.from_descriptor_with_endpoint(bytes.fromhex(request['desc']), peer)
            except ValueError as exc:
                reply({'ok': False, 'error': str(exc)})
                continue
            array = numpy.asarray(buf)
            try:
                array[0] = 0
                write_rejected = False
            except ValueError:
                write_rejected = True
            held[request['key']] = buf
            reply({'ok': True, 'sha': _sha(buf), 'readonly': memoryview(buf).readonly,
                   'write_rejected': write_rejected, 'n': len(buf)})
            del array, buf  # only `held` keeps it
        elif cmd == 'take_drop':
            digests = []
            for hex_desc in request['descs']:
                buf = backend.from_descriptor_with_endpoint(bytes.fromhex(hex_desc), peer)
                digests.append(_sha(buf))
                del buf
            reply({'digests': digests})
        elif cmd == 'sha':
            reply({'sha': _sha(held[request['key']])})
        elif cmd == 'drop':
            held.pop(request['key'], None)
            gc.collect()
            reply({'ok': True})
        elif cmd == 'stats':
            reply(demo_buffer_backend.stats())
        elif cmd == 'sweep':
            demo_buffer_backend.sweep()
            reply({'ok': True})
        elif cmd == 'exit':
            held.clear()
            reply({'ok': True})
            return 0
        else:
            reply({'error': f'unknown command {cmd!r}'})
    return 0


if __name__ == '__main__':
    sys.exit(main())
