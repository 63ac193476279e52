"""CPU settings for the Nature CNN that every algorithm's networks share: which ones make it faster?

One torch thread (what cosim train gives each learner on a 2-core machine) unless
``--threads``; the input is what the learners see: uint8 ``(B, 84, 84, 3K)`` frame stacks
(K = ``--frames``, default 4). Two costs per variant, median of ``--repeats`` batches:

* act: a forward pass for 6 ACs' observations (B = 6, no gradient), as one env step acts;
* update: forward, backward and an Adam step on a batch of 32 (DQN's quick batch) with a
  dueling-sized head, as one gradient step of DQN.

Variants (the network and the data are the same in each; only the layout or the compiler
changes; the outputs are checked to agree with "as today" to 1e-4):

* ``as today``: agents/networks.py NatureCNN, which permutes the channel-last uint8 input to
  NCHW view (its memory is then channels-last) and convolves with NCHW weights;
* ``channels_last``: the convolution weights also channels-last (``model.to(memory_format=
  torch.channels_last)``), so input and weights agree;
* ``contiguous NCHW``: the permuted input copied to contiguous NCHW before the convolutions;
* ``torch.compile``: ``torch.compile(model)`` (inductor; the first calls compile, excluded).

    python bench/cnn_cpu_options.py [--repeats 30] [--threads 1] [--frames 4] [--no-compile]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from torch import nn

from agents.networks import NatureCNN


class _Contiguous(NatureCNN):
    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = (obs.float().permute(0, 3, 1, 2) / 255.0).contiguous()
        return self.linear(self.cnn(x))


def _net(cls, channels: int) -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(cls((84, 84, channels)), nn.Linear(512, 64), nn.ReLU(), nn.Linear(64, 9))


def _time(fn, repeats: int, calls: int) -> float:
    for _ in range(3):
        fn()  # warm-up (and compilation)
    per = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        per.append((time.perf_counter() - t0) / calls)
    return statistics.median(per)


def measure(name: str, net: nn.Module, obs_act, obs_up, repeats: int) -> dict:
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    target = torch.zeros(obs_up.shape[0], 9)

    def act():
        with torch.no_grad():
            net(obs_act)

    def update():
        loss = nn.functional.smooth_l1_loss(net(obs_up), target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return {"variant": name, "act_ms": 1e3 * _time(act, repeats, 10),
            "update_ms": 1e3 * _time(update, repeats, 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--no-compile", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    channels = 3 * args.frames
    gen = torch.Generator().manual_seed(1)
    obs_act = torch.randint(0, 256, (6, 84, 84, channels), dtype=torch.uint8, generator=gen)
    obs_up = torch.randint(0, 256, (32, 84, 84, channels), dtype=torch.uint8, generator=gen)

    base = _net(NatureCNN, channels)
    with torch.no_grad():
        ref = base(obs_act)
    variants = [("as today", base)]
    cl = _net(NatureCNN, channels).to(memory_format=torch.channels_last)
    variants.append(("channels_last", cl))
    variants.append(("contiguous NCHW", _net(_Contiguous, channels)))
    if not args.no_compile:
        variants.append(("torch.compile", torch.compile(_net(NatureCNN, channels))))
    rows = []
    for name, net in variants:
        with torch.no_grad():
            out = net(obs_act)
        if not torch.allclose(out, ref, atol=1e-4):
            raise SystemExit(f"{name}: output differs from 'as today' by {float((out - ref).abs().max()):.2e}")
        rows.append(measure(name, net, obs_act, obs_up, args.repeats))
        print(f"{name}: act {rows[-1]['act_ms']:.2f} ms, update {rows[-1]['update_ms']:.2f} ms", flush=True)
    print(f"\ntorch {torch.__version__}, {args.threads} thread(s), input (B, 84, 84, {channels}) uint8, "
          f"median of {args.repeats} batches\n")
    print("| variant | act, B=6 (ms) | update, B=32 (ms) | act vs today | update vs today |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} | {r['act_ms']:.2f} | {r['update_ms']:.2f} | "
              f"{rows[0]['act_ms'] / r['act_ms']:.2f}x | {rows[0]['update_ms'] / r['update_ms']:.2f}x |")


if __name__ == "__main__":
    main()
