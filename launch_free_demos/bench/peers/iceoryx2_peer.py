"""iceoryx2_peer: the benchmark's frames over iceoryx2's Python bindings (a peer transport).

``python -m launch_free_demos.bench.peers.iceoryx2_peer --role publisher|subscriber --topic NAME
--shm_prefix PREFIX --root_path DIR [image_publisher / image_subscriber parameters]``

A publish-subscribe service of ``Slice[c_uint8]`` named after ``topic``, with a user header
(stamp, counter, CRC32), and an event service of the same name: the publisher loans a sample,
writes the frame into it in place, stamps it, sends it and notifies; the subscriber sleeps in a
WaitSet on the event's listener (no polling), receives every sample and lays a numpy array
over its memory (no copy). See ``common.py`` for what both do on every frame.

Isolation: every file iceoryx2 creates carries ``shm_prefix`` (in /dev/shm) or lives under
``root_path`` (its other files), which the benchmark gives each run; a node that exits normally
removes its own, the benchmark removes what is left (see ``benchmark.remove_peer_files``).
"""
import ctypes
import sys
import time

import iceoryx2 as iox2
import numpy

from launch_free_demos.bench.peers.common import (
    Received, Stop, frame_header, latency_ms, parse_parameters, payload_shape, payload_size,
    pixels, print_report, publish_frames, write_frame)

#: Samples a subscriber may hold and queue (frames come at a low rate, each taken at once).
BUFFER_SIZE = 2


class Header(ctypes.Structure):
    """The user header of every sample: :data:`common.FRAME_HEADER`'s bytes."""
    _pack_ = 1
    _fields_ = [('stamp_ns', ctypes.c_uint64), ('counter', ctypes.c_uint64),
                ('crc', ctypes.c_uint32)]


def open_services(args, subscribers: int):
    """The node, its publish-subscribe service and its event service (opened or created with
    the same settings by either side)."""
    config = iox2.config.default()
    config.global_cfg.prefix = iox2.FileName.new(args.shm_prefix)
    config.global_cfg.root_path = iox2.Path.new(args.root_path)
    node = (iox2.NodeBuilder.new().config(config)
            .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
            .create(iox2.ServiceType.Ipc))
    name = iox2.ServiceName.new(args.topic)
    pubsub = (node.service_builder(name).publish_subscribe(iox2.Slice[ctypes.c_uint8])
              .user_header(Header).max_publishers(1).max_subscribers(subscribers)
              .subscriber_max_buffer_size(BUFFER_SIZE)
              .subscriber_max_borrowed_samples(BUFFER_SIZE).open_or_create())
    event = node.service_builder(name).event().open_or_create()
    return node, pubsub, event


def publish(args, stop: Stop) -> int:
    nbytes = payload_size(args)
    node, pubsub, event = open_services(args, max(args.wait_for_subscribers, 1))
    publisher = pubsub.publisher_builder().initial_max_slice_len(nbytes).create()
    notifier = event.notifier_builder().create()
    source = pixels(nbytes)

    def send(counter: int) -> None:
        sample = publisher.loan_slice_uninit(nbytes)
        target = numpy.frombuffer(sample.payload().as_memory_view(), dtype=numpy.uint8)
        crc = write_frame(target, source, counter)  # in place, in shared memory
        del target
        header = frame_header(counter, crc)  # stamped just before sending
        ctypes.memmove(ctypes.addressof(sample.user_header().contents), header, len(header))
        sample.assume_init().send()
        notifier.notify()

    return publish_frames(args, stop, lambda: pubsub.dynamic_config.number_of_subscribers,
                          send)


def subscribe(args, stop: Stop) -> int:
    shape = payload_shape(args)
    node, pubsub, event = open_services(args, max(args.wait_for_subscribers, 1))
    subscriber = pubsub.subscriber_builder().buffer_size(BUFFER_SIZE).create()
    listener = event.listener_builder().create()
    waitset = (iox2.WaitSetBuilder.new().signal_handling_mode(iox2.SignalHandlingMode.Disabled)
               .create(iox2.ServiceType.Ipc))
    guard = waitset.attach_notification(listener)
    received = Received(args)
    period = args.report_period_sec or 0.25
    next_log = time.monotonic() + period
    while not received.done() and not stop.requested:
        timeout = max(0.0, next_log - time.monotonic())
        waitset.wait_and_process_with_timeout(iox2.Duration.from_secs_f64(timeout))
        listener.try_wait()  # consume the wake-ups, then take every sample there is
        while (sample := subscriber.receive()) is not None:
            started = time.perf_counter_ns()  # the callback starts
            header = bytes(sample.user_header().contents)
            latency = latency_ms(header)
            view = numpy.frombuffer(sample.payload().as_memory_view(),
                                    dtype=numpy.uint8).reshape(shape)
            received.frame(header, latency, time.perf_counter_ns() - started, view, 'iceoryx2')
            del view
            sample.delete()  # return it to the publisher
        if args.report_period_sec and time.monotonic() >= next_log:
            received.log_progress()
            next_log += period
    del guard
    print_report(received.report())
    return 0


def main(argv=None) -> int:
    args = parse_parameters('iceoryx2_peer', argv, extra=(
        ('--shm_prefix', 'prefix of its files in /dev/shm (iceoryx2 global.prefix)'),
        ('--root_path', "directory of iceoryx2's other files (global.root_path)")))
    stop = Stop()
    iox2.set_log_level_from_env_or(iox2.LogLevel.Warn)
    return publish(args, stop) if args.role == 'publisher' else subscribe(args, stop)


if __name__ == '__main__':
    sys.exit(main())
