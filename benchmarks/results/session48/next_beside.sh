#!/usr/bin/env bash
# The forty-eighth session's GPU checks: the forty-seventh session's (session47/next_beside.sh, unchanged), run as
# queue.sh's BESIDE on the second H200 of an nvidia-h200-x2 lease (DEVICE=cuda:1; the queue trained on cuda:0), then
# PrecisionCutting's fixed sine with 4 stacked state frames (next_jobs_beside.txt) on cuda:1. The lease ran a copy of
# that script with this queue (4d776a2); this wrapper does the same.
JOBS=${JOBS:-benchmarks/results/session48/next_jobs_beside.txt} exec bash benchmarks/results/session47/next_beside.sh
