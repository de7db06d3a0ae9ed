"""What a subscriber on loopback may lose (tests that read a running daemon): ZeroMQ's PUB drops for
a subscriber that falls its send high-water mark behind, which a loaded host that starves the test's
loop causes. How many depends on the load: CI lost 1 gyro and 1 raw message of hundreds on one run,
and 3 of 16 frames at 640×480 on another, where the test's own loop also encodes previews. Every such
loss shows as a jump of the topic's seq and is counted; what the bound tells apart is a pattern: a seq
that skipped as it counted would lose about as many as arrive."""

RARE = 0.5                # the share of a topic's received messages that may have been lost


def losses(sub) -> tuple[dict, dict, int]:
    """(gaps, received, restarts) of a `thermod.client.subscriber.Subscriber`, to judge after it closes."""
    return dict(sub.gaps), dict(sub.received), sum(sub.restarts.values())


def rare_losses(gaps: dict, received: dict, restarts: int) -> bool:
    """No seq went back, and no topic lost more than `RARE` of what it received."""
    return restarts == 0 and all(gaps.get(t, 0) <= RARE * n for t, n in received.items())
