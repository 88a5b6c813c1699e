"""A challenge server (``drivebench board``): a leaderboard anyone can submit a brain to, scored on hidden conditions.

store      the submissions and their states, in SQLite in the data folder (schema versioned)
challenge  the conditions (a public part, a hidden part drawn from a secret seed kept in the data folder)
intake     what an upload is (a brain file, a wheel, an ONNX network, a Behavior Metrics brain file), unpacked
scoring    lap success and normalised progress over the hidden conditions with intervals; the ranking
worker     the queue: checking (the brain contract), running (the matrix runner), scored or rejected
evaluate   one evaluation as its own process (``python -m orchestrator.board.evaluate``)
web        the page and the submission API (Starlette, served by uvicorn)
"""
