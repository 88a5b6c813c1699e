"""A drivebench brain process written without drivebench: only ``zenoh``, ``msgpack`` and the standard library.

It is what a team writing its brain in C++ or Rust reimplements: docs/brain-protocol.md is the contract, and the
JSON Schemas in docs/protocol/ describe every message. Join a running stack with

    python examples/standalone_brain/zenoh_brain.py --router tcp/127.0.0.1:7447 --run-id RUN --name line_follower

and drive with it (``drivebench run --attach --brain line_follower``, or a stack started without a brain).

The brain itself is deliberately simple: in the lower half of each RGB frame it finds the red centre line's pixels
(every second row and column), and steers with a PD on the line's offset from the image centre at 8 m/s.
"""

import argparse
import threading
import time

import msgpack
import zenoh

SPEED_MPS = 8.0
KP, KD = 2.0, 3.0


class LineFollower:
    """The driving logic: an RGB frame (bytes, row-major, 3 bytes per pixel) in, (speed m/s, yaw rate rad/s) out."""

    def __init__(self):
        self.previous_error = 0.0

    def reset(self):
        self.previous_error = 0.0

    def act(self, rgb, width, height):
        total = count = 0
        for row in range(height // 2, height, 2):
            start = row * width * 3
            for col in range(0, width, 2):
                r, g, b = rgb[start + 3 * col], rgb[start + 3 * col + 1], rgb[start + 3 * col + 2]
                if r > 80 and r > 2 * g and r > 2 * b:  # saturated red: the centre line
                    total += col
                    count += 1
        if count:
            error = (width / 2.0 - total / count) / (width / 2.0)  # > 0: the line is left of centre
        else:
            error = self.previous_error  # lost it: keep turning the way we were
        yaw_rate = KP * error + KD * (error - self.previous_error)
        self.previous_error = error
        return SPEED_MPS, yaw_rate


class BrainProcess:
    """The wire contract: frames in, one command per frame out, a liveliness token, a control queryable."""

    def __init__(self, session, run_id, name, camera):
        prefix = f"drivebench/run/{run_id}"
        self.run_id, self.name = run_id, name
        self.brain = LineFollower()
        self.episode, self.seq, self.last = -1, 0, None
        self.stopped = threading.Event()
        self.frames = session.declare_subscriber(f"{prefix}/{'sim' if camera == 'raw' else 'noise'}/camera")
        # Commands must never be dropped: the simulator waits for each one in lock-step.
        self.commands = session.declare_publisher(
            f"{prefix}/brain/{name}/cmd", congestion_control=zenoh.CongestionControl.BLOCK
        )
        self.control = session.declare_queryable(f"{prefix}/brain/{name}/control", self.on_control)
        # Declared last: whoever sees the token may rely on everything above.
        self.token = session.liveliness().declare_token(f"drivebench/alive/{run_id}/brain/{name}")

    def on_control(self, query):
        request = msgpack.unpackb(query.payload.to_bytes()) if query.payload is not None else {}
        action = request.get("action")
        reply = {
            "type": "drivebench.ControlReply.v1",
            "ok": action in ("status", "stop"),
            "state": "stopping" if action == "stop" else "serving",
            "episode": self.episode,
            "active_brain": self.name,
        }
        if action not in ("status", "stop"):
            reply["code"] = "unknown_action"  # what a process decides on; detail is for people
            reply["detail"] = f"unknown action {action!r}"
        query.reply(query.key_expr, msgpack.packb(reply))
        if action == "stop":
            self.stopped.set()

    def serve(self):
        while not self.stopped.is_set():
            sample = self.frames.try_recv()
            if sample is None:
                time.sleep(0.001)
                continue
            frame = msgpack.unpackb(sample.payload.to_bytes())
            if frame.get("type") == "drivebench.CameraFrame.v1":
                self.answer(frame)

    def answer(self, frame):
        header = frame["header"]
        if self.last is not None and (self.last["header"]["episode"], self.last["frame_seq"]) == (
            header["episode"],
            header["seq"],
        ):
            self.commands.put(msgpack.packb(self.last))  # the simulator repeated a frame: same answer
            return
        if header["episode"] != self.episode:
            self.episode, self.last = header["episode"], None
            self.brain.reset()
        started = time.perf_counter_ns()
        if frame.get("dropped"):  # lost on the way: keep doing what we last decided
            speed, yaw_rate = (self.last["speed_mps"], self.last["yaw_rate_radps"]) if self.last else (0.0, 0.0)
        else:
            speed, yaw_rate = self.brain.act(frame["data"], frame["width_px"], frame["height_px"])
        command = {
            "type": "drivebench.Command.v1",
            "header": {
                "run_id": self.run_id,
                "episode": header["episode"],
                "seq": self.seq,
                "stamp_ns": header["stamp_ns"],
            },
            "brain": self.name,
            "frame_seq": header["seq"],
            "speed_mps": float(speed),
            "yaw_rate_radps": float(yaw_rate),
            "inference_ns": time.perf_counter_ns() - started,
        }
        self.seq += 1
        self.commands.put(msgpack.packb(command))
        self.last = command


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--router", default="tcp/127.0.0.1:7447", help="the stack's Zenoh router endpoint")
    parser.add_argument("--run-id", required=True, help="the run to drive in")
    parser.add_argument("--name", default="line_follower", help="this brain's name on the bus")
    parser.add_argument(
        "--camera",
        choices=("perturbed", "raw"),
        default="perturbed",
        help="perturbed: after the noise injector (default); raw: straight from the simulator",
    )
    args = parser.parse_args()
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", f'["{args.router}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as session:
        process = BrainProcess(session, args.run_id, args.name, args.camera)
        print(f"brain {args.name} serving run {args.run_id} on {args.router}", flush=True)
        try:
            process.serve()
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
