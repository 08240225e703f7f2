"""An amortised-node SSM's own node encoder as the closed loop's estimator (a feasibility check, not a library
estimator): the state at frame t is the encoder's reading of the ``history`` frames and torques before it (the newest
frame waits for the next step, as in training: a node is read from the samples before it); before ``history`` frames
exist, the first frame is repeated with no torque. Run from the repository root:
    python studies/ukf_in_the_loop/node_encoder_try.py '{"ssm": "runs/.../last.ckpt", "episodes": 20}'"""

import json
import sys

import torch
from estimator_try import try_estimator


class NodeEncoderEstimator:
    def __init__(self, encoder, to_frames, to_inputs):
        self.encoder, self.to_frames, self.to_inputs = encoder, to_frames, to_inputs
        self.h = encoder.history

    def _read(self) -> torch.Tensor:
        return self.encoder(torch.stack(self.ys[-self.h :], 1), torch.stack(self.us[-self.h :], 1))

    def start(self, y):
        y = self.to_frames(y)
        zero = self.to_inputs(torch.zeros(len(y), self.encoder.input_dim))
        self.ys, self.us, self.last = [y] * self.h, [zero] * self.h, y
        return self._read()

    def next(self, u, y):
        self.ys.append(self.last)
        self.us.append(self.to_inputs(u))
        self.ys, self.us, self.last = self.ys[-self.h :], self.us[-self.h :], self.to_frames(y)
        return self._read()


if __name__ == "__main__":
    try_estimator(
        lambda loop: None,
        lambda loop: NodeEncoderEstimator(loop.ssm.node_encoder, loop.to_frames, loop.to_inputs),
        json.loads(sys.argv[1]) if len(sys.argv) > 1 else {},
        "node_encoder_try",
    )
