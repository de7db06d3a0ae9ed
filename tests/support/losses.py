"""What a subscriber on loopback may lose (tests that read a running daemon): ZeroMQ's PUB drops for
a subscriber that falls its send high-water mark behind, which a loaded host that starves the test's
loop causes (CI: 1 gyro and 1 raw message of hundreds). Seqs run on per topic, and a loss is rare,
not a pattern: a seq that skipped as it counted would lose half."""

RARE = 0.1                # the share of a topic's received messages that may have been lost


def losses(sub) -> tuple[dict, dict, int]:
    """(gaps, received, restarts) of a `thermod.client.subscriber.Subscriber`, to judge after it closes."""
    return dict(sub.gaps), dict(sub.received), sum(sub.restarts.values())


def rare_losses(gaps: dict, received: dict, restarts: int) -> bool:
    """No seq went back, and no topic lost more than `RARE` of what it received."""
    return restarts == 0 and all(gaps.get(t, 0) <= RARE * n for t, n in received.items())
