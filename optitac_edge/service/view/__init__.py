"""The live view: what the camera sees, the fiber map, the surface and the contacts, in any browser.

:class:`~optitac_edge.service.view.live.LiveView` takes the frame loop's state
off the frame thread; :class:`~optitac_edge.service.view.server.ViewServer`
serves it with the page shipped in ``assets/``;
:func:`~optitac_edge.service.view.render.render_view` draws it as one picture.
"""
