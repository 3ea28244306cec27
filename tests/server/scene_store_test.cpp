// The scene store in process: revisions as immutable files, the compare-and-set commit, pruning,
// deletion, damaged files, and no acknowledged revision lost when the writer is killed (-9) at
// any moment.

#include "store/scene_store.h"

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <thread>

namespace kdrt::server {
namespace {

namespace fs = std::filesystem;

class SceneStoreTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("kdrt-scene-store-test-" + std::to_string(::getpid()) + "-" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        fs::create_directories(dir_ / "tmp" / "p");
    }
    void TearDown() override { fs::remove_all(dir_); }

    SceneStore store(uint32_t kept = 4) {
        SceneStore s(dir_, dir_ / "tmp" / "p", kept);
        EXPECT_TRUE(s.open().ok());
        return s;
    }

    static proto::SceneDocument scene(const std::string& id, uint64_t revision, size_t n) {
        proto::SceneDocument doc;
        doc.id = id;
        doc.revision = revision;
        for (size_t i = 0; i < n; ++i) {
            proto::SceneInstanceSpec inst;
            inst.mesh = std::string(64, static_cast<char>('a' + i % 6));
            inst.transform.m[3] = static_cast<float>(revision) + 0.5f * static_cast<float>(i);
            doc.instances.push_back(inst);
        }
        return doc;
    }

    fs::path dir_;
};

TEST_F(SceneStoreTest, CreateReadCommitAndList) {
    SceneStore s = store();
    const std::string id = SceneStore::new_id();
    EXPECT_TRUE(proto::is_scene_id(id));
    EXPECT_NE(id, SceneStore::new_id());
    ASSERT_TRUE(s.create(scene(id, 1, 3)).ok());
    auto latest = s.latest(id);
    ASSERT_TRUE(latest.ok());
    EXPECT_EQ(*latest, 1u);
    auto back = s.read(id, 1);
    ASSERT_TRUE(back.ok()) << back.error().detail;
    EXPECT_EQ(*back, scene(id, 1, 3));

    auto committed = s.commit(scene(id, 2, 5));
    ASSERT_TRUE(committed.ok());
    EXPECT_TRUE(*committed);
    // A second writer of revision 2 is stale and changes nothing.
    committed = s.commit(scene(id, 2, 1));
    ASSERT_TRUE(committed.ok());
    EXPECT_FALSE(*committed);
    EXPECT_EQ(s.read(id, 2)->instances.size(), 5u);
    EXPECT_EQ(*s.latest(id), 2u);

    auto ids = s.ids();
    ASSERT_TRUE(ids.ok());
    EXPECT_EQ(*ids, std::vector<std::string>{id});
    EXPECT_GT(s.disk_bytes(id), 0u);

    // Another store object on the same directory (another replica) sees the same.
    SceneStore other(dir_, dir_ / "tmp" / "p", 4);
    EXPECT_EQ(*other.latest(id), 2u);
    EXPECT_EQ(*other.read(id, 2), *s.read(id, 2));
}

/// Files under the store's tmp/p (a staged revision's temp file lives there).
size_t temp_files(const fs::path& dir) {
    size_t n = 0;
    for (const auto& e : fs::directory_iterator(dir / "tmp" / "p")) n += e.is_regular_file();
    return n;
}

TEST_F(SceneStoreTest, AStagedRevisionIsInvisibleUntilCommittedAndGoneWhenDropped) {
    SceneStore s = store();
    const std::string id = SceneStore::new_id();
    ASSERT_TRUE(s.create(scene(id, 1, 3)).ok());
    {
        auto staged = s.stage(scene(id, 2, 3));
        ASSERT_TRUE(staged.ok()) << staged.error().message;
        EXPECT_EQ(temp_files(dir_), 1u);
        EXPECT_FALSE(s.has_revision(id, 2));
        EXPECT_EQ(*s.latest(id), 1u);
    }  // dropped (a refused update): nothing left
    EXPECT_EQ(temp_files(dir_), 0u);
    EXPECT_FALSE(s.has_revision(id, 2));

    auto staged = s.stage(scene(id, 2, 3));
    ASSERT_TRUE(staged.ok());
    auto committed = s.commit(std::move(staged).value());
    ASSERT_TRUE(committed.ok());
    EXPECT_TRUE(*committed);
    EXPECT_EQ(temp_files(dir_), 0u);
    EXPECT_EQ(*s.read(id, 2), scene(id, 2, 3));
    // A staged revision that another writer committed first is stale, its file removed.
    staged = s.stage(scene(id, 2, 1));
    ASSERT_TRUE(staged.ok());
    committed = s.commit(std::move(staged).value());
    ASSERT_TRUE(committed.ok());
    EXPECT_FALSE(*committed);
    EXPECT_EQ(temp_files(dir_), 0u);
    EXPECT_EQ(s.read(id, 2)->instances.size(), 3u);
    // ... and so is one of a scene deleted meanwhile.
    staged = s.stage(scene(id, 3, 3));
    ASSERT_TRUE(staged.ok());
    ASSERT_TRUE(s.remove(id).ok());
    committed = s.commit(std::move(staged).value());
    ASSERT_TRUE(committed.ok());
    EXPECT_FALSE(*committed);
    EXPECT_FALSE(fs::exists(s.scene_dir(id)));
    EXPECT_EQ(temp_files(dir_), 0u);
}

TEST_F(SceneStoreTest, ARevisionEncodedByTheCallerIsStagedAsItsBytes) {
    SceneStore s = store();
    const std::string id = SceneStore::new_id();
    const proto::SceneDocument base = scene(id, 1, 4);
    ASSERT_TRUE(s.create(base).ok());
    // A pose update's file, encoded from the base and the poses (no document made for it).
    proto::Transform moved;
    moved.m = {0, -1, 0, 3, 1, 0, 0, -2, 0, 0, 2, 0.5f};
    const std::vector<proto::ResolvedPose> poses = {{3, moved}, {0, moved}};
    const std::vector<std::byte> bytes = proto::encode_scene_file(base, 2, poses);
    auto staged = s.stage(id, 2, bytes);
    ASSERT_TRUE(staged.ok()) << staged.error().message;
    EXPECT_FALSE(s.has_revision(id, 2));
    auto committed = s.commit(std::move(staged).value());
    ASSERT_TRUE(committed.ok());
    EXPECT_TRUE(*committed);
    EXPECT_EQ(temp_files(dir_), 0u);
    std::ifstream in(s.revision_path(id, 2), std::ios::binary);
    const std::string on_disk((std::istreambuf_iterator<char>(in)),
                              std::istreambuf_iterator<char>());
    ASSERT_EQ(on_disk.size(), bytes.size());
    EXPECT_EQ(std::memcmp(on_disk.data(), bytes.data(), bytes.size()), 0);
    proto::SceneDocument expected = base;
    expected.revision = 2;
    expected.instances[0].transform = moved;
    expected.instances[3].transform = moved;
    auto back = s.read(id, 2);
    ASSERT_TRUE(back.ok()) << back.error().detail;
    EXPECT_EQ(*back, expected);
    // The same compare-and-set as a staged document: a second revision 2 is stale.
    staged = s.stage(id, 2, proto::encode_scene_file(base, 2, {}));
    ASSERT_TRUE(staged.ok());
    committed = s.commit(std::move(staged).value());
    ASSERT_TRUE(committed.ok());
    EXPECT_FALSE(*committed);
    EXPECT_EQ(*s.read(id, 2), expected);
    EXPECT_EQ(temp_files(dir_), 0u);
}

TEST_F(SceneStoreTest, MissingScenesAndRevisions) {
    SceneStore s = store();
    const std::string id = SceneStore::new_id();
    EXPECT_EQ(s.latest(id).error().code, SceneStoreError::Code::kMissing);
    EXPECT_EQ(s.read(id, 1).error().code, SceneStoreError::Code::kMissing);
    auto committed = s.commit(scene(id, 2, 1));
    ASSERT_TRUE(committed.ok());
    EXPECT_FALSE(*committed) << "no revision 2 of a scene that does not exist";
    EXPECT_FALSE(fs::exists(s.scene_dir(id)));
    auto removed = s.remove(id);
    ASSERT_TRUE(removed.ok());
    EXPECT_EQ(removed->outcome, SceneStore::Removal::Outcome::kMissing);
}

TEST_F(SceneStoreTest, KeepsTheNewestRevisionsOnly) {
    SceneStore s = store(3);
    const std::string id = SceneStore::new_id();
    ASSERT_TRUE(s.create(scene(id, 1, 1)).ok());
    for (uint64_t r = 2; r <= 7; ++r) ASSERT_TRUE(*s.commit(scene(id, r, 1)));
    for (uint64_t r = 1; r <= 7; ++r)
        EXPECT_TRUE(s.has_revision(id, r)) << r << ": a commit deletes nothing (the answer first)";
    s.prune(id, 7);
    for (uint64_t r = 1; r <= 4; ++r) EXPECT_FALSE(s.has_revision(id, r)) << r;
    for (uint64_t r = 5; r <= 7; ++r) EXPECT_TRUE(s.has_revision(id, r)) << r;
    EXPECT_EQ(s.read(id, 2).error().code, SceneStoreError::Code::kMissing);
    EXPECT_EQ(*s.latest(id), 7u);
}

TEST_F(SceneStoreTest, RevisionsAreKdrsAndJsonRevisionsOfOlderStoresStillRead) {
    SceneStore s = store();
    const std::string id = SceneStore::new_id();
    ASSERT_TRUE(s.create(scene(id, 1, 3)).ok());
    ASSERT_TRUE(*s.commit(scene(id, 2, 3)));
    for (const uint64_t r : {1, 2}) {
        std::ifstream f(s.revision_path(id, r), std::ios::binary);
        std::string magic(4, '\0');
        f.read(magic.data(), 4);
        EXPECT_EQ(magic, "KDRS") << r;
    }
    // A scene as the previous version stored it: its revisions in JSON, under the same names.
    const std::string old = SceneStore::new_id();
    fs::create_directories(s.scene_dir(old));
    for (const uint64_t r : {1, 2}) {
        std::ofstream f(s.revision_path(old, r), std::ios::binary);
        f << proto::encode_scene_json(scene(old, r, 4));
    }
    EXPECT_EQ(*s.latest(old), 2u);
    for (const uint64_t r : {1, 2}) {
        auto doc = s.read(old, r);
        ASSERT_TRUE(doc.ok()) << doc.error().detail;
        EXPECT_EQ(*doc, scene(old, r, 4));
    }
    ASSERT_TRUE(*s.commit(scene(old, 3, 4)));
    EXPECT_FALSE(*s.commit(scene(old, 2, 4))) << "the JSON revision 2 takes its name";
    auto next = s.read(old, 3);
    ASSERT_TRUE(next.ok()) << next.error().detail;
    EXPECT_EQ(*next, scene(old, 3, 4));
}

// Two stores on one directory (two replicas sharing it) create scenes from many threads at once
// against max_scenes: the count and the rename are under the store's create lock, so the store
// never holds more (counting first and creating after lets two creates pass it by one each).
TEST_F(SceneStoreTest, ConcurrentCreatesOnTwoReplicasNeverPassMaxScenes) {
    constexpr size_t kMax = 3;
    fs::create_directories(dir_ / "tmp" / "q");
    SceneStore a = store(), b(dir_, dir_ / "tmp" / "q", 4);
    ASSERT_TRUE(b.open().ok());
    for (int round = 0; round < 20; ++round) {
        std::atomic<size_t> created{0}, refused{0};
        std::vector<std::thread> threads;
        for (int t = 0; t < 8; ++t)
            threads.emplace_back([&, t] {
                SceneStore& s = t % 2 == 0 ? a : b;
                for (int k = 0; k < 2; ++k) {
                    auto r = s.create(scene(SceneStore::new_id(), 1, 1), kMax);
                    ASSERT_TRUE(r.ok()) << r.error().message;
                    if (r->created) {
                        created++;
                    } else {
                        EXPECT_GE(r->scenes, kMax);
                        refused++;
                    }
                }
            });
        for (auto& t : threads) t.join();
        const auto ids = a.ids();
        ASSERT_TRUE(ids.ok());
        ASSERT_EQ(ids->size(), kMax) << "round " << round;
        EXPECT_EQ(created.load(), kMax);
        EXPECT_EQ(refused.load(), 16 - kMax);
        for (const std::string& id : *ids) ASSERT_TRUE(b.remove(id).ok());
    }
    EXPECT_TRUE(fs::is_empty(dir_ / "tmp" / "p"));
    EXPECT_TRUE(fs::is_empty(dir_ / "tmp" / "q"));
}

TEST_F(SceneStoreTest, RemoveDeletesEveryRevisionAtOnce) {
    SceneStore s = store();
    const std::string a = SceneStore::new_id(), b = SceneStore::new_id();
    ASSERT_TRUE(s.create(scene(a, 1, 1)).ok());
    ASSERT_TRUE(s.create(scene(b, 1, 2)).ok());
    ASSERT_TRUE(*s.commit(scene(a, 2, 1)));
    auto removed = s.remove(a);
    ASSERT_TRUE(removed.ok());
    EXPECT_EQ(removed->outcome, SceneStore::Removal::Outcome::kRemoved);
    EXPECT_EQ(s.latest(a).error().code, SceneStoreError::Code::kMissing);
    EXPECT_FALSE(*s.commit(scene(a, 3, 1))) << "a deleted scene takes no revision";
    EXPECT_EQ(*s.ids(), std::vector<std::string>{b});
    EXPECT_TRUE(fs::is_empty(dir_ / "tmp" / "p"));
}

TEST_F(SceneStoreTest, AConditionalRemoveDeletesOnlyTheCurrentRevision) {
    using Outcome = SceneStore::Removal::Outcome;
    SceneStore s = store();
    const std::string id = SceneStore::new_id();
    ASSERT_TRUE(s.create(scene(id, 1, 1)).ok());
    ASSERT_TRUE(*s.commit(scene(id, 2, 1)));
    auto stale = s.remove(id, 1);
    ASSERT_TRUE(stale.ok());
    EXPECT_EQ(stale->outcome, Outcome::kStale);
    EXPECT_EQ(stale->current, 2u);
    EXPECT_EQ(*s.latest(id), 2u) << "a stale conditional remove deletes nothing";
    auto removed = s.remove(id, 2);
    ASSERT_TRUE(removed.ok());
    EXPECT_EQ(removed->outcome, Outcome::kRemoved);
    EXPECT_EQ(s.latest(id).error().code, SceneStoreError::Code::kMissing);
    auto again = s.remove(id, 2);
    ASSERT_TRUE(again.ok());
    EXPECT_EQ(again->outcome, Outcome::kMissing);
}

TEST_F(SceneStoreTest, AConditionalRemoveAndACommitOfTheSameBaseNeverBothWin) {
    // Two stores on one directory, as two replicas sharing the store (each its own tmp/): one
    // commits revision 2 while the other deletes on "If-Match: 1". Exactly one of them wins.
    using Outcome = SceneStore::Removal::Outcome;
    fs::create_directories(dir_ / "tmp" / "q");
    SceneStore a = store();
    SceneStore b(dir_, dir_ / "tmp" / "q", 4);
    ASSERT_TRUE(b.open().ok());
    int commits_won = 0, removes_won = 0;
    for (int round = 0; round < 100; ++round) {
        const std::string id = SceneStore::new_id();
        ASSERT_TRUE(a.create(scene(id, 1, 2)).ok());
        std::atomic<int> ready{0};
        proto::Result<bool, WriteError> committed = false;
        proto::Result<SceneStore::Removal, WriteError> removed = SceneStore::Removal{};
        std::thread writer([&] {
            ++ready;
            while (ready < 2) {
            }
            committed = a.commit(scene(id, 2, 2));
        });
        ++ready;
        while (ready < 2) {
        }
        removed = b.remove(id, 1);
        writer.join();
        ASSERT_TRUE(committed.ok()) << committed.error().message;
        ASSERT_TRUE(removed.ok()) << removed.error().message;
        if (*committed) {
            ++commits_won;
            EXPECT_EQ(removed->outcome, Outcome::kStale) << "round " << round;
            EXPECT_EQ(removed->current, 2u);
            EXPECT_EQ(*a.latest(id), 2u) << "an acknowledged revision was deleted";
            ASSERT_EQ(b.remove(id)->outcome, Outcome::kRemoved);
        } else {
            ++removes_won;
            EXPECT_EQ(removed->outcome, Outcome::kRemoved) << "round " << round;
            EXPECT_EQ(a.latest(id).error().code, SceneStoreError::Code::kMissing);
        }
    }
    std::printf("commit first %d, remove first %d of 100\n", commits_won, removes_won);
    for (const auto& entry : fs::directory_iterator(dir_ / "scenes"))  // no scene left
        EXPECT_EQ(entry.path().filename(), ".create-lock");
}

TEST_F(SceneStoreTest, DamagedRevisionsAreReportedNotServed) {
    SceneStore s = store();
    const std::string id = SceneStore::new_id(), other = SceneStore::new_id();
    ASSERT_TRUE(s.create(scene(id, 1, 2)).ok());
    ASSERT_TRUE(s.create(scene(other, 1, 2)).ok());
    {
        std::ofstream f(s.revision_path(id, 1), std::ios::binary | std::ios::trunc);
        f << "{\"format\":\"kdrt-scene\",\"id\":";
    }
    auto bad = s.read(id, 1);
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error().code, SceneStoreError::Code::kCorrupt);
    EXPECT_NE(bad.error().detail.find(s.revision_path(id, 1).string()), std::string::npos);
    // A revision file of another scene copied in place.
    fs::copy_file(s.revision_path(other, 1), s.revision_path(id, 1),
                  fs::copy_options::overwrite_existing);
    bad = s.read(id, 1);
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error().code, SceneStoreError::Code::kCorrupt);
    EXPECT_NE(bad.error().detail.find("holds revision 1 of scene " + other), std::string::npos);
}

TEST_F(SceneStoreTest, ConcurrentWritersOfOneRevisionCommitExactlyOnce) {
    SceneStore s = store(1000);
    const std::string id = SceneStore::new_id();
    ASSERT_TRUE(s.create(scene(id, 1, 1)).ok());
    // Each thread reads the latest revision and tries to write the next, as a pose update does;
    // every revision is committed by exactly one thread.
    std::atomic<int> committed{0}, stale{0};
    std::vector<std::thread> threads;
    for (int t = 0; t < 4; ++t)
        threads.emplace_back([&, t] {
            for (int i = 0; i < 25; ++i) {
                const uint64_t base = *s.latest(id);
                auto r = s.commit(scene(id, base + 1, static_cast<size_t>(t) + 1));
                ASSERT_TRUE(r.ok());
                (*r ? committed : stale)++;
            }
        });
    for (auto& t : threads) t.join();
    EXPECT_EQ(*s.latest(id), 1u + static_cast<uint64_t>(committed.load()));
    for (uint64_t r = 1; r <= *s.latest(id); ++r) EXPECT_TRUE(s.read(id, r).ok()) << r;
}

// A child process creates scenes and commits revisions as fast as it can, writing each
// acknowledged (scene, revision) to a pipe only after the store returned; the parent kills it
// with SIGKILL at a varying moment, then checks with a fresh store that every acknowledged
// revision is there and reads back whole, and that nothing half-written is visible.
TEST_F(SceneStoreTest, NoAcknowledgedRevisionIsLostOnKillMinus9) {
    constexpr int kRounds = 12;
    std::vector<std::pair<std::string, uint64_t>> acknowledged;
    for (int round = 0; round < kRounds; ++round) {
        int fds[2];
        ASSERT_EQ(::pipe(fds), 0);
        const pid_t pid = ::fork();
        ASSERT_GE(pid, 0);
        if (pid == 0) {
            ::close(fds[0]);
            SceneStore s(dir_, dir_ / "tmp" / "p", 1u << 20);
            if (!s.open()) ::_exit(2);
            for (int k = 0;; ++k) {
                const std::string id = SceneStore::new_id();
                if (!s.create(scene(id, 1, 3))) ::_exit(3);
                std::string line = id + " 1\n";
                if (::write(fds[1], line.data(), line.size()) < 0) ::_exit(4);
                for (uint64_t r = 2; r < 40; ++r) {
                    auto c = s.commit(scene(id, r, 3 + r % 5));
                    if (!c || !*c) ::_exit(5);
                    line = id + " " + std::to_string(r) + "\n";
                    if (::write(fds[1], line.data(), line.size()) < 0) ::_exit(4);
                }
            }
        }
        ::close(fds[1]);
        std::this_thread::sleep_for(std::chrono::milliseconds(5 + 7 * round));
        ::kill(pid, SIGKILL);
        int status = 0;
        ::waitpid(pid, &status, 0);
        ASSERT_TRUE(WIFSIGNALED(status))
            << "the writer failed by itself: exit " << WEXITSTATUS(status);
        std::string text;
        char buf[4096];
        for (ssize_t n; (n = ::read(fds[0], buf, sizeof buf)) > 0;)
            text.append(buf, static_cast<size_t>(n));
        ::close(fds[0]);
        for (size_t at = 0, end; (end = text.find('\n', at)) != std::string::npos; at = end + 1) {
            const std::string line = text.substr(at, end - at);
            acknowledged.emplace_back(line.substr(0, 32), std::stoull(line.substr(33)));
        }
    }
    ASSERT_GT(acknowledged.size(), static_cast<size_t>(kRounds));
    SceneStore s = store(1u << 20);
    for (const auto& [id, revision] : acknowledged) {
        auto doc = s.read(id, revision);
        ASSERT_TRUE(doc.ok()) << id << " revision " << revision << ": " << doc.error().detail;
        EXPECT_EQ(*doc, scene(id, revision, revision == 1 ? 3 : 3 + revision % 5));
        EXPECT_GE(*s.latest(id), revision);
    }
    // Every scene visible after the crashes reads back whole at every revision it lists.
    const auto ids = s.ids();
    ASSERT_TRUE(ids.ok());
    for (const std::string& id : *ids) {
        const uint64_t latest = *s.latest(id);
        for (uint64_t r = 1; r <= latest; ++r)
            EXPECT_TRUE(s.read(id, r).ok()) << id << " revision " << r;
    }
}

}  // namespace
}  // namespace kdrt::server
