"""The command-line tools: the recorder (:mod:`.record`), the player (:mod:`.play`), the MCAP
bag format in rosbag2's profile (:mod:`.bag`, :mod:`.message_definition`), :mod:`.bag_info`,
:mod:`.reindex` and the topic inspector (:mod:`.info`). They build on the library; the library
never imports them."""
