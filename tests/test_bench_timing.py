"""The benchmarks' turn-taking timer: which calls are timed and in what order."""

from benchmarks.timing import round_robin, samples_in_turn


def test_calls_in_turn_with_untimed_rounds_and_warm_calls():
    seen: list[tuple[str, int]] = []
    fns = {"a": lambda i: seen.append(("a", i)), "b": lambda i: seen.append(("b", i))}
    t = samples_in_turn(fns, repeats=3, block=2, warmup=1, warm=1)
    # 1 untimed round + 3 rounds, each 1 warm + 2 timed calls of a, then of b
    assert len(seen) == 4 * 2 * 3
    assert [n for n, _ in seen[:6]] == ["a"] * 3 + ["b"] * 3
    assert [i for _, i in seen] == list(range(24))  # one running call index
    for wall, cpu in t.values():
        assert len(wall) == len(cpu) == 3 * 2
        assert all(w >= 0 for w in wall) and all(c >= 0 for c in cpu)


def test_round_robin_medians_and_minima_of_the_timed_calls():
    fns = {"a": lambda i: None}
    med, low = round_robin(fns, repeats=5, block=3, with_min=True)
    assert set(med) == set(low) == {"a"} and 0 <= low["a"] <= med["a"]
