"""When the reader wakes by itself for the next sample due (server/runs/reader.py,
`next_publication`): with a dashboard taking telemetry it wakes just after the loop publishes the
sample due to be sent, not for the samples the decimation skips (issue 30 item 4), and follows
the doorbell where that time is not known."""

from __future__ import annotations

from xrflab.server.runs.reader import next_publication

MS = 1_000_000
PERIOD_30HZ = 1_000_000_000 // 30


def test_the_wake_up_is_at_the_publication_of_the_sample_due() -> None:
    # A RELbot publishes every 20 ms (50 Hz); dashboards get 30 Hz. Last sample read at 100 ms,
    # the next one due at 133.3 ms: published at 140 ms (the second after 100 ms).
    assert next_publication(100 * MS + PERIOD_30HZ, 100 * MS, 20 * MS, PERIOD_30HZ) == 140 * MS
    # Due exactly at a publication: that one.
    assert next_publication(140 * MS, 100 * MS, 20 * MS, PERIOD_30HZ) == 140 * MS
    # A loop publishing slower than the dashboards' rate: the next publication.
    assert next_publication(100 * MS + PERIOD_30HZ, 100 * MS, 50 * MS, PERIOD_30HZ) == 150 * MS


def test_the_wake_up_is_at_the_sample_that_completes_a_message() -> None:
    """Two samples a message (Settings.telemetry_per_message): the reader wakes for the second
    sample due, not for the first (`message_due_at`), ~15 times a second instead of 30."""
    from xrflab.server.runs.reader import message_due_at

    # Last sample read (and sent) at 100 ms, the next due at 133.3: the one after it due at 166.7,
    # published at 180 ms. With one of the two already read: the next due, at 140 ms.
    assert message_due_at(100 * MS + PERIOD_30HZ, 0, 2, 100 * MS, 20 * MS, PERIOD_30HZ) == 180 * MS
    assert message_due_at(100 * MS + PERIOD_30HZ, 1, 2, 100 * MS, 20 * MS, PERIOD_30HZ) == 140 * MS
    # One sample a message: next_publication's answer.
    assert message_due_at(100 * MS + PERIOD_30HZ, 0, 1, 100 * MS, 20 * MS, PERIOD_30HZ) == 140 * MS
    # The spacing unknown: the doorbell, as for one sample.
    assert message_due_at(100 * MS + PERIOD_30HZ, 0, 2, 100 * MS, 0, PERIOD_30HZ) == 0


def test_the_doorbell_without_what_it_needs() -> None:
    assert next_publication(133 * MS, 100 * MS, 0, PERIOD_30HZ) == 0  # spacing unknown (first sample)
    assert next_publication(100 * MS, 100 * MS, 20 * MS, PERIOD_30HZ) == 0  # the next sample is due already
    assert next_publication(90 * MS, 100 * MS, 20 * MS, PERIOD_30HZ) == 0
    # A sample due far beyond a period (a gap in the loop's publications): the doorbell.
    assert next_publication(100 * MS + 10 * PERIOD_30HZ, 100 * MS, 20 * MS, PERIOD_30HZ) == 0


def test_the_console_poll_goes_with_a_reader_wake_up() -> None:
    """With a dashboard taking monitor lines the output poll (10 a second) waits for the reader's
    first wake-up past its due time (`with_reader`, `output_due`), so it costs no wake-up of the
    event loop of its own; not before it is due, and its own timer only if the reader never
    wakes."""
    import asyncio
    import time
    from types import SimpleNamespace

    from xrflab.server.runs.reader import output_due, with_reader

    async def main() -> None:
        run = SimpleNamespace(output_due=0.0, output_poll=asyncio.Event(), output_fd=-1, output_read=0)
        waiting = asyncio.create_task(with_reader(run, 30.0))  # type: ignore[arg-type]  # its own timer: 45 s
        await asyncio.sleep(0)  # the task registers what it waits for
        assert run.output_due > time.monotonic() + 29
        output_due(run, time.monotonic())  # a reader wake-up before it is due: nothing
        await asyncio.sleep(0)  # one turn of the event loop: had it been let go, it would have run
        assert not waiting.done()
        output_due(run, run.output_due)  # the first wake-up at or past it: the poll goes now
        await asyncio.wait_for(waiting, 1.0)
        assert run.output_due == 0.0  # nobody waits any more: the reader lets nothing go
        run.output_poll.clear()
        output_due(run, time.monotonic())
        assert not run.output_poll.is_set()

        # The reader does not wake (simulated time paused, a stalled loop): the poll's own timer.
        late = asyncio.create_task(with_reader(run, 0.02))  # type: ignore[arg-type]
        await asyncio.wait_for(late, 1.0)

    asyncio.run(main())


def test_with_nobody_taking_monitor_lines_the_output_poll_waits_for_the_reader(tmp_path) -> None:
    """With nobody taking monitor lines the loop's output file is polled at the reader's idle
    batch (`with_reader`, OUTPUT_IDLE_S), not on a timer of its own once a second (issue 30 item
    4, session 14); a reader wake-up past it lets the poll go, and so does the run's end (the
    reader's last batch); its own timer only after OUTPUT_IDLE_LATEST_S. A real file, a hub with
    no client."""
    import asyncio
    import time
    from types import SimpleNamespace

    from xrflab.server.runs import reader
    from xrflab.server.runs.launch import OUTPUT
    from xrflab.server.ws.hub import Hub

    (tmp_path / OUTPUT).write_bytes(b"hello\n")

    async def main() -> None:
        run = SimpleNamespace(
            run_dir=tmp_path,
            alive=True,
            output_due=0.0,
            output_poll=asyncio.Event(),
            row=SimpleNamespace(id=1),
            output_fd=-1,
            output_read=0,
        )
        task = asyncio.create_task(reader.pipe_output(run, Hub()))  # type: ignore[arg-type]
        await asyncio.sleep(0.05)  # its first poll, then its wait
        due = run.output_due
        assert due > time.monotonic() + reader.OUTPUT_IDLE_S - 0.5, (
            "with nobody taking monitor lines the output poll waits on a timer of its own, not for the reader"
        )
        reader.output_due(run, time.monotonic())  # a reader wake-up before it is due: nothing
        await asyncio.sleep(0.05)  # on purpose: a turn of the event loop for the poll task (it must not go)
        assert run.output_due == due and not task.done()
        # The reader's wake-ups past it: the file has not grown since the poll read it, so the
        # poll does not go (no step of its task for an unchanged file: session 16) ...
        assert run.output_read == len(b"hello\n") and run.output_fd >= 0
        reader.output_due(run, due + 1)
        await asyncio.sleep(0.05)  # on purpose: a turn of the event loop for the poll task (it must not go)
        assert run.output_due == due and not run.output_poll.is_set()
        with (tmp_path / OUTPUT).open("ab") as out:  # ... until the loop writes more
            out.write(b"more\n")
        reader.output_due(run, due)  # the reader's first wake-up past it: the poll goes, then waits again
        for _ in range(500):  # (up to 5 s: the poll reads the run's output off the event loop)
            if run.output_due > due:
                break
            await asyncio.sleep(0.01)
        assert run.output_due > due, "the reader's wake-up did not let the poll go"
        assert run.output_read == len(b"hello\nmore\n")
        run.alive = False
        run.output_poll.set()  # the run's end (the reader's last batch): the last output read, done
        await asyncio.wait_for(task, 2.0)
        assert run.output_fd == -1  # the file closed with the task: nothing looks at its number

    asyncio.run(main())
