"""The watch's pure part: the plant's drift estimated from the loop's samples against the
rig's twin (`estimate`), and judged against the plant knowledge's bound (`judge`). The process
that runs it beside the controller is `controller.process.watch`."""
