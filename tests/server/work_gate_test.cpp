// WorkGate (renders, builds) and ByteBudget (ray batches): the admission bounds of service.h.

#include <gtest/gtest.h>

#include <atomic>
#include <thread>

#include "service.h"

namespace kdrt::server {
namespace {

/// Spins (bounded) until `predicate` holds; the threads below only need to reach a wait.
template <typename Predicate>
bool eventually(Predicate predicate) {
    for (int i = 0; i < 200000 && !predicate(); ++i) std::this_thread::yield();
    return predicate();
}

TEST(WorkGate, RunsTheLimitQueuesTheNextAndRefusesTheRest) {
    WorkGate gate(1, 1);
    const std::atomic<bool> stop{false};
    auto first = gate.enter(stop);
    ASSERT_TRUE(first);
    EXPECT_EQ(gate.running(), 1u);
    std::atomic<bool> second_in{false};
    std::thread second([&] {
        auto slot = gate.enter(stop);
        second_in = slot.has_value();
    });
    ASSERT_TRUE(eventually([&] { return gate.waiting() == 1; }));
    EXPECT_FALSE(gate.enter(stop)) << "the queue (1) is full: refused at once";
    first.reset();  // the waiter takes the slot
    second.join();
    EXPECT_TRUE(second_in);
    EXPECT_EQ(gate.running(), 0u);
    EXPECT_EQ(gate.waiting(), 0u);
    EXPECT_TRUE(gate.enter(stop));
}

TEST(WorkGate, WaitersLeaveWhenStopped) {
    WorkGate gate(1, 4);
    std::atomic<bool> stop{false};
    auto held = gate.enter(stop);
    ASSERT_TRUE(held);
    std::atomic<int> refused{0};
    std::thread a([&] { refused += gate.enter(stop) ? 0 : 1; });
    std::thread b([&] { refused += gate.enter(stop) ? 0 : 1; });
    ASSERT_TRUE(eventually([&] { return gate.waiting() == 2; }));
    stop = true;
    a.join();
    b.join();
    EXPECT_EQ(refused, 2);
}

TEST(ByteBudget, TakesWhatFitsAndGivesItBack) {
    ByteBudget budget(100);
    auto a = budget.try_take(60);
    ASSERT_TRUE(a);
    EXPECT_FALSE(budget.try_take(41));
    EXPECT_FALSE(budget.try_take(101));
    auto b = budget.try_take(40);
    ASSERT_TRUE(b);
    EXPECT_EQ(budget.held(), 100u);
    a.reset();
    EXPECT_EQ(budget.held(), 40u);
    EXPECT_TRUE(budget.try_take(60));
}

}  // namespace
}  // namespace kdrt::server
