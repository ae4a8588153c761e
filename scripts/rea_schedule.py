#!/usr/bin/env python3
"""Makespan of `Rea::run_pool`'s schedule on W workers, in units of one candidate evaluation.

Model: every evaluation takes the same time t; the initial population (P candidates) goes out
first; then cycle c (population = ids c .. c+P-1, tournament = k of them drawn uniformly) is sent
as soon as all of its tournament members are evaluated, looking at most P cycles past the lowest
cycle not yet sent (the rule of search/src/rea.rs). Tournaments here come from Python's
generator, not the search's ChaCha streams: the makespan is a statistic over 20 seeds.
Usage: scripts/rea_schedule.py [P cycles k W...]   (default: Table S1, P 100, 150 cycles, k 10)
"""
import heapq
import random
import sys


def makespan(P, C, k, W, seed):
    rng = random.Random(seed)
    tours = [rng.sample(range(P), k) for _ in range(C)]
    done, events, pending = set(), [], list(range(C))
    t, nxt_init, busy = 0.0, 0, 0
    while True:
        while busy < W and nxt_init < P:
            heapq.heappush(events, (t + 1.0, nxt_init))
            nxt_init, busy = nxt_init + 1, busy + 1
        if busy < W and pending:
            lo = pending[0]
            for c in list(pending):
                if busy >= W or c >= lo + P:
                    break
                if all(c + pos in done for pos in tours[c]):
                    heapq.heappush(events, (t + 1.0, P + c))
                    pending.remove(c)
                    busy += 1
        if not events:
            return t
        t, i = heapq.heappop(events)
        done.add(i)
        busy -= 1
        while events and events[0][0] == t:
            done.add(heapq.heappop(events)[1])
            busy -= 1


def main():
    a = [int(x) for x in sys.argv[1:]]
    P, C, k = a[:3] if len(a) >= 3 else (100, 150, 10)
    workers = a[3:] or [1, 2, 8, 16, 64]
    for W in workers:
        ms = [makespan(P, C, k, W, s) for s in range(20)]
        m = sum(ms) / len(ms)
        print(f"W {W:4d}: {m:6.1f} t (seeds: {min(ms):.0f}..{max(ms):.0f}), "
              f"speedup {(P + C) / m:5.2f}, without the wait {-(-P // W) + -(-C // W)} t")


if __name__ == "__main__":
    main()
