"""What the learner trains against: the BatchedEnv protocol (protocol.py), the env factory that builds the
drone env over a corpus or the toy env (factory.py), the toy env for tests (toy.py), and a remote env that
flies a `navi serve env` over Zenoh (remote.py).
"""
