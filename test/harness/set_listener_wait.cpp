// Fast DDS 2.14 as PyPI ships it: DomainParticipant::set_listener while a discovery callback
// runs (see src/native/README.md, "Never Fast DDS's default wait in set_listener").
//
// Participant A's listener sleeps 300 ms in its first discovery callback (participant B found);
// meanwhile main sets A's listener to nullptr, with the default wait ("forever") or a bounded
// one (1 s). Built and run against the venv's libraries:
//
//   L=.venv/lib; S=.venv/lib/python3.11/site-packages/ros_fastrtps.libs
//   g++ -std=c++17 -O2 test/harness/set_listener_wait.cpp -I.venv/include -L$L \
//       -Wl,-rpath-link,$S -lfastrtps -lfastcdr -o /tmp/set_listener_wait
//   LD_LIBRARY_PATH=$L:$S timeout 20 /tmp/set_listener_wait default 91   # never returns
//   LD_LIBRARY_PATH=$L:$S timeout 20 /tmp/set_listener_wait bounded 92   # 0.3 s, ~0 CPU
#include <atomic>
#include <chrono>
#include <cstdio>
#include <ctime>
#include <string>
#include <thread>
#include "fastdds/dds/domain/DomainParticipant.hpp"
#include "fastdds/dds/domain/DomainParticipantFactory.hpp"
#include "fastdds/dds/domain/DomainParticipantListener.hpp"

using namespace eprosima::fastdds::dds;
std::atomic<bool> in_callback{false};
std::atomic<bool> callback_done{false};

struct Slow : DomainParticipantListener
{
  void on_participant_discovery(
    DomainParticipant *, eprosima::fastrtps::rtps::ParticipantDiscoveryInfo &&) override
  {
    if (!in_callback.exchange(true)) {
      std::this_thread::sleep_for(std::chrono::milliseconds(300));
      callback_done = true;
    }
  }
};

int main(int argc, char ** argv)
{
  const bool bounded = argc > 1 && std::string(argv[1]) == "bounded";
  const int domain = argc > 2 ? std::stoi(argv[2]) : 90;
  auto * factory = DomainParticipantFactory::get_instance();
  Slow slow;
  DomainParticipant * a = factory->create_participant(domain, PARTICIPANT_QOS_DEFAULT, &slow);
  DomainParticipant * b = factory->create_participant(domain, PARTICIPANT_QOS_DEFAULT);
  while (!in_callback) {std::this_thread::sleep_for(std::chrono::milliseconds(1));}
  const auto wall0 = std::chrono::steady_clock::now();
  const std::clock_t cpu0 = std::clock();
  auto rc = bounded ? a->set_listener(nullptr, std::chrono::seconds(1)) : a->set_listener(nullptr);
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count();
  const double cpu = double(std::clock() - cpu0) / CLOCKS_PER_SEC;
  std::printf("%s: set_listener returned %d after %.3f s wall, %.3f s CPU (callback %s)\n",
    bounded ? "bounded wait" : "default wait", int(rc()), wall, cpu,
    callback_done ? "done" : "not done");
  std::fflush(stdout);
  factory->delete_participant(b);
  factory->delete_participant(a);
  return 0;
}
